//! SIMD ray packets: eight or sixteen rays of a tile marched through one volume in lockstep.
//!
//! Each lane is one ray with its own lattice index, band, brick cursor and macrocell. The
//! control flow of the scalar march ([`crate::raycast`]) runs per lane, in scalar code, up to
//! the point where the lane has the page coordinate of its next sample: locating bricks,
//! jumping over transparent bricks and invisible macrocells, moving to the next band. A
//! lane whose next sample needs none of that (it lies short of the segment's end and the
//! brick's exit, in the same macrocell or a visible next one) takes a lockstep step instead
//! (`Fast`): its `t`, index position, page coordinate and macrocell crossing computed all
//! lanes wide. What every lane then does alike, the trilinear interpolation (gathers from
//! the atlas slots, in the slots' own element type), the transfer-function lookup (all
//! bands' tables laid end to end; a lane's two neighbouring entries are one 32-byte load,
//! and eight such loads are transposed into channels across lanes) and the front-to-back
//! blend, runs all lanes at a time.
//!
//! **Two widths, one march.** The march is written once over a `Vector` trait of
//! operations: eight lanes with AVX2 and sixteen with AVX-512 (F and DQ), chosen at run
//! time ([`lanes_for`], `render.simd_lanes`). Sixteen lanes give the core two independent
//! halves of each step's long chain (gathers, lookup, blend) to overlap.
//!
//! **Same image, bit for bit.** Every lane performs the scalar caster's operations in the
//! same order with the same roundings (no fused multiply-adds, truncating conversions as
//! `as` does), so a packet of either width gives exactly the pixels, counters and page
//! requests the scalar march gives; tests compare them bit for bit. The packet path needs
//! AVX2 (detected at run time); without it, with gradient shading, pre-integration or f64
//! accumulation, with several volumes, or with an atlas or transfer-function table too
//! large for 32-bit gather indices, the scalar march runs (`render.simd = false` forces
//! it). A single volume invisible under its transfer function is not marched at all.

use crate::atlas::Samples;
use crate::feedback::Requests;
use crate::raycast::{FrameSetup, RayState};
use crate::volume::{first_k, first_k_near, Cursor, VolFrame};

/// Lanes of the widest packet.
pub const MAX_LANES: usize = 16;

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
    widest() > 0
}

/// The widest packet this CPU runs: 16 lanes with AVX-512 (F and DQ) and AVX2, 8 with AVX2,
/// else 0 (no packets).
pub fn widest() -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx2") && has!("avx512f") && has!("avx512dq") {
            16
        } else if has!("avx2") {
            8
        } else {
            0
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        0
    }
}

/// The packet width for `render.simd_lanes`: 0 asks for the widest this CPU runs; 8 or 16
/// for that width, or the widest below it that the CPU runs (16 → 8 without AVX-512).
/// 0 without packets.
pub fn lanes_for(requested: u32) -> usize {
    let w = widest();
    // (Other values are refused by the engine's settings check; they get 8 lanes here
    // rather than a width no march exists for.)
    match requested {
        0 | 16 => w,
        _ => w.min(8),
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
    /// `volume::octant(md)`.
    oct: usize,
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
    /// The lane of ray `w.ray` over its pending interval.
    fn new(f: &FrameSetup<'_>, r: &RayState<'_, '_>, w: &Pending) -> Lane {
        let md = r.md0();
        let band = f.bands.at(w.ta);
        Lane {
            ray: w.ray,
            live: true,
            cur: r.cursor().clone(),
            md,
            inv: md.map(|m| 1.0 / m),
            oct: crate::volume::octant(md),
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
    }

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
                let (visible, exit) = v.cell_run_at(cur, l, md, self.inv, self.oct);
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
/// sample came from [`Lane::next`] takes its next one here, all lanes wide, while `k·dt` stays
/// short of `hard` (the segment's end and the brick's exit), crossing into the next
/// macrocell here too when that cell is visible, and goes back to `Lane::next` for the step
/// that reaches a segment end, a brick boundary or an invisible cell.
#[derive(Default)]
struct Fast {
    /// −1 where the lane's state is here (its `Lane::k` is then stale), else 0.
    on: [i32; MAX_LANES],
    /// The lattice index of the lane's next sample.
    k: [i32; MAX_LANES],
    dt: [f32; MAX_LANES],
    /// The lesser of the segment's end and the brick's exit (−∞ if either is NaN: `t < NaN`
    /// fails where `min` would not).
    hard: [f32; MAX_LANES],
    /// The macrocell's exit (+∞ without macrocells).
    cell: [f32; MAX_LANES],
    md: [[f32; MAX_LANES]; 3],
    /// `1 / md`, as the lane's `inv`.
    inv: [[f32; MAX_LANES]; 3],
    /// The cursor's index → slot scale, its inverse and offsets, its slot and the slot's
    /// first element.
    s: [f32; MAX_LANES],
    rs: [f32; MAX_LANES],
    o: [[f32; MAX_LANES]; 3],
    slot: [u32; MAX_LANES],
    off: [i32; MAX_LANES],
    band: [i32; MAX_LANES],
    /// Samples taken here (added to the lane's at the end).
    count: [i32; MAX_LANES],
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

/// Marches up to `f.lanes` rays of a tile (`rays[p.ray]` for each `p` in `work`) through
/// the frame's single volume, each over its pending interval, and leaves every ray exactly
/// as its scalar march would.
pub fn march(
    f: &FrameSetup<'_>,
    rays: &mut [RayState<'_, '_>],
    work: &[Pending],
    fb: &mut Requests,
) {
    debug_assert!(work.len() <= f.lanes && f.vols.len() == 1 && f.lanes <= widest());
    let v = &f.vols[0];
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the engine sets `f.lanes` from `lanes_for`, which gives 16 only where AVX-512
    // F and DQ and AVX2 were detected and 8 only where AVX2 was.
    unsafe {
        macro_rules! by_type {
            ($m:ident) => {
                match v.samples {
                    Samples::F32(d) => x86::$m::<f32>(f, v, d, rays, work, fb),
                    Samples::U8(d) => x86::$m::<u8>(f, v, d, rays, work, fb),
                    Samples::I8(d) => x86::$m::<i8>(f, v, d, rays, work, fb),
                    Samples::U16(d) => x86::$m::<u16>(f, v, d, rays, work, fb),
                    Samples::I16(d) => x86::$m::<i16>(f, v, d, rays, work, fb),
                }
            };
        }
        match f.lanes {
            16 => by_type!(march16),
            8 => by_type!(march8),
            n => unreachable!("no packets of {n} lanes"),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (v, rays, work, fb);
        unreachable!("packets are only chosen where AVX2 exists");
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;
    use crate::atlas::Voxel;
    use std::arch::x86_64::*;

    /// One SIMD width's operations, for [`march_body`], written once for every width.
    ///
    /// Each operation is one instruction (or a fixed short sequence) with the rounding the
    /// scalar march has; `M` is a lane mask. Callers run inside a function with the width's
    /// target features enabled (`march8`, `march16`), into which these inline.
    pub(super) trait Vector: Copy {
        /// Lanes.
        const N: usize;
        type F: Copy;
        type I: Copy;
        type M: Copy;
        unsafe fn splat_f(x: f32) -> Self::F;
        unsafe fn splat_i(x: i32) -> Self::I;
        /// Loads `N` f32 (unaligned).
        unsafe fn load_f(p: *const f32) -> Self::F;
        /// Loads `N` i32 (unaligned).
        unsafe fn load_i(p: *const i32) -> Self::I;
        unsafe fn store_f(p: *mut f32, v: Self::F);
        unsafe fn store_i(p: *mut i32, v: Self::I);
        unsafe fn add_f(a: Self::F, b: Self::F) -> Self::F;
        unsafe fn sub_f(a: Self::F, b: Self::F) -> Self::F;
        unsafe fn mul_f(a: Self::F, b: Self::F) -> Self::F;
        /// `a < b ? a : b` per lane (`minps`: `b` where either is NaN).
        unsafe fn min_f(a: Self::F, b: Self::F) -> Self::F;
        /// `a > b ? a : b` per lane (`maxps`: `b` where either is NaN).
        unsafe fn max_f(a: Self::F, b: Self::F) -> Self::F;
        /// i32 → f32, rounding to nearest (as `as f32`).
        unsafe fn to_f(a: Self::I) -> Self::F;
        /// f32 → i32, truncating (as `as i32` in range).
        unsafe fn to_i(a: Self::F) -> Self::I;
        unsafe fn add_i(a: Self::I, b: Self::I) -> Self::I;
        unsafe fn mul_i(a: Self::I, b: Self::I) -> Self::I;
        unsafe fn min_i(a: Self::I, b: Self::I) -> Self::I;
        /// Logical shift right by 4.
        unsafe fn shr4(a: Self::I) -> Self::I;
        /// Shift left by 2.
        unsafe fn shl2(a: Self::I) -> Self::I;
        /// `a < b` (ordered: false with a NaN).
        unsafe fn lt(a: Self::F, b: Self::F) -> Self::M;
        /// `a > b` (ordered).
        unsafe fn gt(a: Self::F, b: Self::F) -> Self::M;
        /// `a >= b` (ordered).
        unsafe fn ge(a: Self::F, b: Self::F) -> Self::M;
        /// `a != b` (unordered: true with a NaN, as Rust's `!=`).
        unsafe fn ne(a: Self::F, b: Self::F) -> Self::M;
        /// Neither is NaN.
        unsafe fn ord(a: Self::F, b: Self::F) -> Self::M;
        unsafe fn eq_i(a: Self::I, b: Self::I) -> Self::M;
        /// The mask of lanes holding −1 (every lane holds −1 or 0).
        unsafe fn mask_of(a: Self::I) -> Self::M;
        unsafe fn and_m(a: Self::M, b: Self::M) -> Self::M;
        unsafe fn or_m(a: Self::M, b: Self::M) -> Self::M;
        /// `!a & b`.
        unsafe fn andnot_m(a: Self::M, b: Self::M) -> Self::M;
        /// One bit per lane, lane 0 lowest.
        unsafe fn bits(m: Self::M) -> u32;
        /// `m ? b : a` per lane.
        unsafe fn select_f(m: Self::M, a: Self::F, b: Self::F) -> Self::F;
        /// `m ? b : a` per lane.
        unsafe fn select_i(m: Self::M, a: Self::I, b: Self::I) -> Self::I;
        /// `x` where `m`, +0 elsewhere (bits kept exactly).
        unsafe fn keep_f(x: Self::F, m: Self::M) -> Self::F;
        /// `x` where `m`, 0 elsewhere.
        unsafe fn keep_i(x: Self::I, m: Self::M) -> Self::I;
        /// `x + 1` where `m`.
        unsafe fn inc_i(x: Self::I, m: Self::M) -> Self::I;
        /// The transfer-function entries at float offset `ei[i]` of `lut` (entry e, then
        /// e + 1: eight consecutive floats per lane), as channels across lanes: `(RGBA of
        /// e, RGBA of e + 1)`.
        ///
        /// # Safety
        /// Every `ei[i] + 8` of the first `N` is within the table.
        unsafe fn lut(lut: *const f32, ei: &[i32; MAX_LANES]) -> ([Self::F; 4], [Self::F; 4]);
    }

    /// Eight lanes: AVX2 (masks are all-ones or all-zero lanes of a `__m256`).
    #[derive(Copy, Clone)]
    pub(super) struct V8;

    /// Sixteen lanes: AVX-512 F and DQ (masks are `__mmask16`).
    #[derive(Copy, Clone)]
    pub(super) struct V16;

    /// Eight lanes' entries `e` and `e + 1` (32 bytes from `lut + ei[i]`), one load per lane
    /// and an 8 × 8 transpose into channels across lanes (cheaper than eight gathers):
    /// `(RGBA of e, RGBA of e + 1)`.
    #[inline(always)]
    unsafe fn lut8(lut: *const f32, ei: &[i32]) -> ([__m256; 4], [__m256; 4]) {
        unsafe {
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
            // Channel c of entry e in column c of `u`, of entry e + 1 in column c + 4.
            // (Macros, not closures: everything must inline into the caller's features.)
            macro_rules! lo {
                ($u:expr, $w:expr) => {
                    _mm256_permute2f128_ps::<0x20>($u, $w)
                };
            }
            macro_rules! hi {
                ($u:expr, $w:expr) => {
                    _mm256_permute2f128_ps::<0x31>($u, $w)
                };
            }
            (
                [lo!(u0, u4), lo!(u1, u5), lo!(u2, u6), lo!(u3, u7)],
                [hi!(u0, u4), hi!(u1, u5), hi!(u2, u6), hi!(u3, u7)],
            )
        }
    }

    // The operations are one intrinsic each; they inline into `march8` (AVX2 enabled).
    #[allow(clippy::missing_safety_doc)]
    impl Vector for V8 {
        const N: usize = 8;
        type F = __m256;
        type I = __m256i;
        type M = __m256;
        #[inline(always)]
        unsafe fn splat_f(x: f32) -> __m256 {
            unsafe { _mm256_set1_ps(x) }
        }
        #[inline(always)]
        unsafe fn splat_i(x: i32) -> __m256i {
            unsafe { _mm256_set1_epi32(x) }
        }
        #[inline(always)]
        unsafe fn load_f(p: *const f32) -> __m256 {
            unsafe { _mm256_loadu_ps(p) }
        }
        #[inline(always)]
        unsafe fn load_i(p: *const i32) -> __m256i {
            unsafe { _mm256_loadu_si256(p as *const __m256i) }
        }
        #[inline(always)]
        unsafe fn store_f(p: *mut f32, v: __m256) {
            unsafe { _mm256_storeu_ps(p, v) }
        }
        #[inline(always)]
        unsafe fn store_i(p: *mut i32, v: __m256i) {
            unsafe { _mm256_storeu_si256(p as *mut __m256i, v) }
        }
        #[inline(always)]
        unsafe fn add_f(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_add_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn sub_f(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_sub_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn mul_f(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_mul_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn min_f(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_min_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn max_f(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_max_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn to_f(a: __m256i) -> __m256 {
            unsafe { _mm256_cvtepi32_ps(a) }
        }
        #[inline(always)]
        unsafe fn to_i(a: __m256) -> __m256i {
            unsafe { _mm256_cvttps_epi32(a) }
        }
        #[inline(always)]
        unsafe fn add_i(a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_add_epi32(a, b) }
        }
        #[inline(always)]
        unsafe fn mul_i(a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_mullo_epi32(a, b) }
        }
        #[inline(always)]
        unsafe fn min_i(a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_min_epi32(a, b) }
        }
        #[inline(always)]
        unsafe fn shr4(a: __m256i) -> __m256i {
            unsafe { _mm256_srli_epi32::<4>(a) }
        }
        #[inline(always)]
        unsafe fn shl2(a: __m256i) -> __m256i {
            unsafe { _mm256_slli_epi32::<2>(a) }
        }
        #[inline(always)]
        unsafe fn lt(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn gt(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_GT_OQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn ge(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_GE_OQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn ne(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_NEQ_UQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn ord(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_ORD_Q>(a, b) }
        }
        #[inline(always)]
        unsafe fn eq_i(a: __m256i, b: __m256i) -> __m256 {
            unsafe { _mm256_castsi256_ps(_mm256_cmpeq_epi32(a, b)) }
        }
        #[inline(always)]
        unsafe fn mask_of(a: __m256i) -> __m256 {
            unsafe { _mm256_castsi256_ps(a) }
        }
        #[inline(always)]
        unsafe fn and_m(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_and_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn or_m(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_or_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn andnot_m(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_andnot_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn bits(m: __m256) -> u32 {
            unsafe { _mm256_movemask_ps(m) as u32 }
        }
        #[inline(always)]
        unsafe fn select_f(m: __m256, a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_blendv_ps(a, b, m) }
        }
        #[inline(always)]
        unsafe fn select_i(m: __m256, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_blendv_epi8(a, b, _mm256_castps_si256(m)) }
        }
        #[inline(always)]
        unsafe fn keep_f(x: __m256, m: __m256) -> __m256 {
            unsafe { _mm256_and_ps(x, m) }
        }
        #[inline(always)]
        unsafe fn keep_i(x: __m256i, m: __m256) -> __m256i {
            unsafe { _mm256_and_si256(x, _mm256_castps_si256(m)) }
        }
        #[inline(always)]
        unsafe fn inc_i(x: __m256i, m: __m256) -> __m256i {
            // A true lane is −1.
            unsafe { _mm256_sub_epi32(x, _mm256_castps_si256(m)) }
        }
        #[inline(always)]
        unsafe fn lut(lut: *const f32, ei: &[i32; MAX_LANES]) -> ([__m256; 4], [__m256; 4]) {
            unsafe { lut8(lut, &ei[..8]) }
        }
    }

    // The operations are one intrinsic each; they inline into `march16` (AVX-512 F and DQ
    // enabled, and AVX2 for the table's transposes).
    #[allow(clippy::missing_safety_doc)]
    impl Vector for V16 {
        const N: usize = 16;
        type F = __m512;
        type I = __m512i;
        type M = __mmask16;
        #[inline(always)]
        unsafe fn splat_f(x: f32) -> __m512 {
            unsafe { _mm512_set1_ps(x) }
        }
        #[inline(always)]
        unsafe fn splat_i(x: i32) -> __m512i {
            unsafe { _mm512_set1_epi32(x) }
        }
        #[inline(always)]
        unsafe fn load_f(p: *const f32) -> __m512 {
            unsafe { _mm512_loadu_ps(p) }
        }
        #[inline(always)]
        unsafe fn load_i(p: *const i32) -> __m512i {
            unsafe { _mm512_loadu_si512(p as *const _) }
        }
        #[inline(always)]
        unsafe fn store_f(p: *mut f32, v: __m512) {
            unsafe { _mm512_storeu_ps(p, v) }
        }
        #[inline(always)]
        unsafe fn store_i(p: *mut i32, v: __m512i) {
            unsafe { _mm512_storeu_si512(p as *mut _, v) }
        }
        #[inline(always)]
        unsafe fn add_f(a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_add_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn sub_f(a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_sub_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn mul_f(a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_mul_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn min_f(a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_min_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn max_f(a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_max_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn to_f(a: __m512i) -> __m512 {
            unsafe { _mm512_cvtepi32_ps(a) }
        }
        #[inline(always)]
        unsafe fn to_i(a: __m512) -> __m512i {
            unsafe { _mm512_cvttps_epi32(a) }
        }
        #[inline(always)]
        unsafe fn add_i(a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_add_epi32(a, b) }
        }
        #[inline(always)]
        unsafe fn mul_i(a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_mullo_epi32(a, b) }
        }
        #[inline(always)]
        unsafe fn min_i(a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_min_epi32(a, b) }
        }
        #[inline(always)]
        unsafe fn shr4(a: __m512i) -> __m512i {
            unsafe { _mm512_srli_epi32::<4>(a) }
        }
        #[inline(always)]
        unsafe fn shl2(a: __m512i) -> __m512i {
            unsafe { _mm512_slli_epi32::<2>(a) }
        }
        #[inline(always)]
        unsafe fn lt(a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn gt(a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_GT_OQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn ge(a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_GE_OQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn ne(a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(a, b) }
        }
        #[inline(always)]
        unsafe fn ord(a: __m512, b: __m512) -> __mmask16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_ORD_Q>(a, b) }
        }
        #[inline(always)]
        unsafe fn eq_i(a: __m512i, b: __m512i) -> __mmask16 {
            unsafe { _mm512_cmpeq_epi32_mask(a, b) }
        }
        #[inline(always)]
        unsafe fn mask_of(a: __m512i) -> __mmask16 {
            unsafe { _mm512_cmpneq_epi32_mask(a, _mm512_setzero_si512()) }
        }
        #[inline(always)]
        unsafe fn and_m(a: __mmask16, b: __mmask16) -> __mmask16 {
            a & b
        }
        #[inline(always)]
        unsafe fn or_m(a: __mmask16, b: __mmask16) -> __mmask16 {
            a | b
        }
        #[inline(always)]
        unsafe fn andnot_m(a: __mmask16, b: __mmask16) -> __mmask16 {
            !a & b
        }
        #[inline(always)]
        unsafe fn bits(m: __mmask16) -> u32 {
            m as u32
        }
        #[inline(always)]
        unsafe fn select_f(m: __mmask16, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_mask_blend_ps(m, a, b) }
        }
        #[inline(always)]
        unsafe fn select_i(m: __mmask16, a: __m512i, b: __m512i) -> __m512i {
            unsafe { _mm512_mask_blend_epi32(m, a, b) }
        }
        #[inline(always)]
        unsafe fn keep_f(x: __m512, m: __mmask16) -> __m512 {
            unsafe { _mm512_maskz_mov_ps(m, x) }
        }
        #[inline(always)]
        unsafe fn keep_i(x: __m512i, m: __mmask16) -> __m512i {
            unsafe { _mm512_maskz_mov_epi32(m, x) }
        }
        #[inline(always)]
        unsafe fn inc_i(x: __m512i, m: __mmask16) -> __m512i {
            unsafe { _mm512_mask_add_epi32(x, m, x, _mm512_set1_epi32(1)) }
        }
        #[inline(always)]
        unsafe fn lut(lut: *const f32, ei: &[i32; MAX_LANES]) -> ([__m512; 4], [__m512; 4]) {
            unsafe {
                // Two eight-lane transposes, joined.
                let (a0, b0) = lut8(lut, &ei[..8]);
                let (a1, b1) = lut8(lut, &ei[8..]);
                macro_rules! join {
                    ($l:expr, $h:expr) => {
                        _mm512_insertf32x8::<1>(_mm512_castps256_ps512($l), $h)
                    };
                }
                (
                    [
                        join!(a0[0], a1[0]),
                        join!(a0[1], a1[1]),
                        join!(a0[2], a1[2]),
                        join!(a0[3], a1[3]),
                    ],
                    [
                        join!(b0[0], b1[0]),
                        join!(b0[1], b1[1]),
                        join!(b0[2], b1[2]),
                        join!(b0[3], b1[3]),
                    ],
                )
            }
        }
    }

    /// Gathers the samples at element `i` and `i + 1` of every lane from a slot array.
    pub(super) trait GatherPair<V: Vector>: Voxel {
        /// # Safety
        /// The CPU has the width's features; every `i + 1` (and, for 8-bit types, `i + 3`)
        /// is inside the array `base` points to.
        unsafe fn pair(base: *const Self, i: V::I) -> (V::F, V::F);
    }

    impl GatherPair<V8> for f32 {
        #[inline(always)]
        unsafe fn pair(base: *const f32, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let a = _mm256_i32gather_ps::<4>(base, i);
                let b = _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(i, _mm256_set1_epi32(1)));
                (a, b)
            }
        }
    }

    impl GatherPair<V8> for u8 {
        #[inline(always)]
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

    impl GatherPair<V8> for i8 {
        #[inline(always)]
        unsafe fn pair(base: *const i8, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let w = _mm256_i32gather_epi32::<1>(base as *const i32, i);
                let a = _mm256_srai_epi32::<24>(_mm256_slli_epi32::<24>(w));
                let b = _mm256_srai_epi32::<24>(_mm256_slli_epi32::<16>(w));
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair<V8> for u16 {
        #[inline(always)]
        unsafe fn pair(base: *const u16, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let w = _mm256_i32gather_epi32::<2>(base as *const i32, i);
                let a = _mm256_and_si256(w, _mm256_set1_epi32(0xffff));
                let b = _mm256_srli_epi32::<16>(w);
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair<V8> for i16 {
        #[inline(always)]
        unsafe fn pair(base: *const i16, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let w = _mm256_i32gather_epi32::<2>(base as *const i32, i);
                let a = _mm256_srai_epi32::<16>(_mm256_slli_epi32::<16>(w));
                let b = _mm256_srai_epi32::<16>(w);
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair<V16> for f32 {
        #[inline(always)]
        unsafe fn pair(base: *const f32, i: __m512i) -> (__m512, __m512) {
            unsafe {
                let a = _mm512_i32gather_ps::<4>(i, base);
                let b = _mm512_i32gather_ps::<4>(_mm512_add_epi32(i, _mm512_set1_epi32(1)), base);
                (a, b)
            }
        }
    }

    impl GatherPair<V16> for u8 {
        #[inline(always)]
        unsafe fn pair(base: *const u8, i: __m512i) -> (__m512, __m512) {
            unsafe {
                let w = _mm512_i32gather_epi32::<1>(i, base as *const i32);
                let m = _mm512_set1_epi32(0xff);
                let a = _mm512_and_si512(w, m);
                let b = _mm512_and_si512(_mm512_srli_epi32::<8>(w), m);
                (_mm512_cvtepi32_ps(a), _mm512_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair<V16> for i8 {
        #[inline(always)]
        unsafe fn pair(base: *const i8, i: __m512i) -> (__m512, __m512) {
            unsafe {
                let w = _mm512_i32gather_epi32::<1>(i, base as *const i32);
                let a = _mm512_srai_epi32::<24>(_mm512_slli_epi32::<24>(w));
                let b = _mm512_srai_epi32::<24>(_mm512_slli_epi32::<16>(w));
                (_mm512_cvtepi32_ps(a), _mm512_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair<V16> for u16 {
        #[inline(always)]
        unsafe fn pair(base: *const u16, i: __m512i) -> (__m512, __m512) {
            unsafe {
                let w = _mm512_i32gather_epi32::<2>(i, base as *const i32);
                let a = _mm512_and_si512(w, _mm512_set1_epi32(0xffff));
                let b = _mm512_srli_epi32::<16>(w);
                (_mm512_cvtepi32_ps(a), _mm512_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair<V16> for i16 {
        #[inline(always)]
        unsafe fn pair(base: *const i16, i: __m512i) -> (__m512, __m512) {
            unsafe {
                let w = _mm512_i32gather_epi32::<2>(i, base as *const i32);
                let a = _mm512_srai_epi32::<16>(_mm512_slli_epi32::<16>(w));
                let b = _mm512_srai_epi32::<16>(w);
                (_mm512_cvtepi32_ps(a), _mm512_cvtepi32_ps(b))
            }
        }
    }

    /// Eight lanes with AVX2.
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn march8<T: GatherPair<V8>>(
        f: &FrameSetup<'_>,
        v: &VolFrame<'_>,
        data: &[T],
        rays: &mut [RayState<'_, '_>],
        work: &[Pending],
        fb: &mut Requests,
    ) {
        unsafe { march_body::<V8, T>(f, v, data, rays, work, fb) }
    }

    /// Sixteen lanes with AVX-512.
    ///
    /// # Safety
    /// The CPU has AVX2, AVX-512 F and AVX-512 DQ.
    #[target_feature(enable = "avx2,avx512f,avx512dq")]
    pub(super) unsafe fn march16<T: GatherPair<V16>>(
        f: &FrameSetup<'_>,
        v: &VolFrame<'_>,
        data: &[T],
        rays: &mut [RayState<'_, '_>],
        work: &[Pending],
        fb: &mut Requests,
    ) {
        unsafe { march_body::<V16, T>(f, v, data, rays, work, fb) }
    }

    /// `a + f·(b − a)`, as the scalar code evaluates it.
    #[inline(always)]
    unsafe fn lerp<V: Vector>(a: V::F, b: V::F, f: V::F) -> V::F {
        unsafe { V::add_f(a, V::mul_f(f, V::sub_f(b, a))) }
    }

    /// The march, for any width: inlined into `march8` and `march16`, whose features the
    /// operations need.
    #[inline(always)]
    unsafe fn march_body<V: Vector, T: GatherPair<V>>(
        f: &FrameSetup<'_>,
        v: &VolFrame<'_>,
        data: &[T],
        rays: &mut [RayState<'_, '_>],
        work: &[Pending],
        fb: &mut Requests,
    ) {
        let n = V::N;
        debug_assert!(work.len() <= n && n <= MAX_LANES);
        let p = v.page;
        // Gathers index with i32: the pool and the tables must fit (the engine chooses the
        // packet path only then).
        assert!(data.len() < i32::MAX as usize && v.flat.rgba.len() < i32::MAX as usize);
        let mut lanes: Vec<Lane> = work.iter().map(|w| Lane::new(f, &rays[w.ray], w)).collect();
        let mut acc = [[0.0f32; MAX_LANES]; 4];
        // Each lane's own termination threshold (lower under cross-worker occlusion).
        let mut erts = [f.ert; MAX_LANES];
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
        let mut live_bits: u32 = (1 << lanes.len()) - 1;
        // SAFETY (all operations below): the width's features are enabled in the caller
        // this inlines into; every gather index is in bounds as argued where it is formed.
        unsafe {
            let mut ar = V::load_f(acc[0].as_ptr());
            let mut ag = V::load_f(acc[1].as_ptr());
            let mut ab = V::load_f(acc[2].as_ptr());
            let mut aa = V::load_f(acc[3].as_ptr());
            let ert = V::load_f(erts.as_ptr());
            let one = V::splat_f(1.0);
            let zero = V::splat_f(0.0);
            let lut = v.flat.rgba.as_ptr();
            let (sy, sz) = (p as i32, (p * p) as i32);
            let vc = [V::splat_f(v.c[0]), V::splat_f(v.c[1]), V::splat_f(v.c[2])];
            let maxc = V::splat_f((p - 1) as f32 - 1e-3);
            loop {
                // The fast lanes' next sample: `t = k·dt` short of the segment's end, the
                // brick's exit and the macrocell's exit, so the scalar `Lane::next` would
                // do no more than compute `l` as `VolFrame::local` does (same operations,
                // same order) and count the sample (or, at the cell's exit, also find the
                // next cell visible, below). Lanes outside those bounds run it.
                let kv = V::load_i(fast.k.as_ptr());
                let t = V::mul_f(V::to_f(kv), V::load_f(fast.dt.as_ptr()));
                let below = V::and_m(
                    V::mask_of(V::load_i(fast.on.as_ptr())),
                    V::lt(t, V::load_f(fast.hard.as_ptr())),
                );
                let in_cell = V::lt(t, V::load_f(fast.cell.as_ptr()));
                let mut go = V::and_m(below, in_cell);
                let s_v = V::load_f(fast.s.as_ptr());
                // (A macro: the operations must inline into this function's features.)
                macro_rules! local {
                    ($a:expr) => {{
                        let q = V::add_f(vc[$a], V::mul_f(t, V::load_f(fast.md[$a].as_ptr())));
                        let l = V::add_f(V::mul_f(q, s_v), V::load_f(fast.o[$a].as_ptr()));
                        // `f32::clamp(0, maxc)`: below 0 → 0, then above maxc → maxc.
                        let l = V::select_f(V::lt(l, zero), l, zero);
                        V::select_f(V::gt(l, maxc), l, maxc)
                    }};
                }
                let l3 = [local!(0), local!(1), local!(2)];
                // Lanes at their macrocell's exit (inside the brick and the segment): the
                // next cell as `VolFrame::cell_at` finds it; into a visible one the lane
                // samples here, an invisible one is skipped by `Lane::next`.
                let cross = V::andnot_m(in_cell, below);
                if let (Some(cells), true) = (v.cells, V::bits(cross) != 0) {
                    let nc = v.cells_per_axis;
                    // `l as usize / CELL` (`l` is clamped to [0, p − 1)); CELL is 2⁴.
                    const _: () = assert!(crate::macrocell::CELL == 16);
                    let ci = [
                        V::shr4(V::to_i(l3[0])),
                        V::shr4(V::to_i(l3[1])),
                        V::shr4(V::to_i(l3[2])),
                    ];
                    let vn = V::splat_i(nc as i32);
                    let idx = V::add_i(V::mul_i(V::add_i(V::mul_i(ci[2], vn), ci[1]), vn), ci[0]);
                    let mut exit = V::splat_f(f32::INFINITY);
                    let cell = V::splat_i(crate::macrocell::CELL as i32);
                    let rs_v = V::load_f(fast.rs.as_ptr());
                    for a in (0..3).rev() {
                        let dir = V::mul_f(V::load_f(fast.md[a].as_ptr()), s_v);
                        let lo = V::mul_i(ci[a], cell);
                        let hi = V::add_i(lo, cell);
                        let bound = V::to_f(V::select_i(V::gt(dir, zero), lo, hi));
                        let e = V::mul_f(
                            V::sub_f(
                                V::mul_f(V::sub_f(bound, V::load_f(fast.o[a].as_ptr())), rs_v),
                                vc[a],
                            ),
                            V::load_f(fast.inv[a].as_ptr()),
                        );
                        // `dir != 0.0` as the scalar code has it. Where it holds, `e` is not
                        // NaN (`Fast::take` admits only lanes with finite `md`, and finite
                        // `inv` where `md` is not 0), so `min_f` is `f32::min` here.
                        exit = V::select_f(V::ne(dir, zero), exit, V::min_f(exit, e));
                    }
                    let (mut idxs, mut exits) = ([0i32; MAX_LANES], [0.0f32; MAX_LANES]);
                    V::store_i(idxs.as_mut_ptr(), idx);
                    V::store_f(exits.as_mut_ptr(), exit);
                    let bits = V::bits(cross);
                    let mut into = [0i32; MAX_LANES];
                    for i in 0..n {
                        if bits >> i & 1 == 1 {
                            let c = fast.slot[i] as usize * nc * nc * nc + idxs[i] as usize;
                            if cells[c] != 0 {
                                fast.cell[i] = exits[i];
                                into[i] = -1;
                            }
                        }
                    }
                    go = V::or_m(go, V::mask_of(V::load_i(into.as_ptr())));
                }
                let go_bits = V::bits(go);
                // k + 1 and one more sample where a fast lane sampled.
                V::store_i(fast.k.as_mut_ptr(), V::inc_i(kv, go));
                V::store_i(
                    fast.count.as_mut_ptr(),
                    V::inc_i(V::load_i(fast.count.as_ptr()), go),
                );
                // The band of the ready lanes if they share one (`MIXED`: they do not).
                const MIXED: usize = usize::MAX - 1;
                let mut bands = [0usize; MAX_LANES];
                // Where every live lane has a lockstep sample (nearly every step), the
                // sample positions stay in registers and no lane runs scalar code.
                let band0 = fast.band[(go_bits.trailing_zeros() as usize).min(n - 1)];
                let same_band = V::bits(V::eq_i(V::load_i(fast.band.as_ptr()), V::splat_i(band0)))
                    & go_bits
                    == go_bits;
                let (x, y, z, offs, mask, common) =
                    if go_bits != 0 && go_bits == live_bits && same_band {
                        (
                            V::keep_f(l3[0], go),
                            V::keep_f(l3[1], go),
                            V::keep_f(l3[2], go),
                            V::keep_i(V::load_i(fast.off.as_ptr()), go),
                            go,
                            band0 as usize,
                        )
                    } else {
                        let (mut lx, mut ly, mut lz) = (
                            [0.0f32; MAX_LANES],
                            [0.0f32; MAX_LANES],
                            [0.0f32; MAX_LANES],
                        );
                        let mut offs = [0i32; MAX_LANES];
                        // Lanes without a lockstep sample read the start of slot 0 (in bounds)
                        // unless the scalar march gives them one below.
                        V::store_f(lx.as_mut_ptr(), V::keep_f(l3[0], go));
                        V::store_f(ly.as_mut_ptr(), V::keep_f(l3[1], go));
                        V::store_f(lz.as_mut_ptr(), V::keep_f(l3[2], go));
                        V::store_i(
                            offs.as_mut_ptr(),
                            V::keep_i(V::load_i(fast.off.as_ptr()), go),
                        );
                        let mut on = [0i32; MAX_LANES];
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
                            V::load_f(lx.as_ptr()),
                            V::load_f(ly.as_ptr()),
                            V::load_f(lz.as_ptr()),
                            V::load_i(offs.as_ptr()),
                            V::mask_of(V::load_i(on.as_ptr())),
                            common,
                        )
                    };
                // Each lane's band table: one broadcast when the lanes share a band (nearly
                // always), else per lane. Masked lanes take the same (their lookups stay
                // inside that band's table).
                let (base, scale, offset, last, maxi) = if common != MIXED {
                    let b = &v.flat.bands[common];
                    (
                        V::splat_i(b.base as i32),
                        V::splat_f(b.scale),
                        V::splat_f(b.offset),
                        V::splat_f(b.last),
                        V::splat_i(b.len as i32 - 2),
                    )
                } else {
                    let mut base = [0i32; MAX_LANES];
                    let mut scale = [0.0f32; MAX_LANES];
                    let mut offset = [0.0f32; MAX_LANES];
                    let mut last = [0.0f32; MAX_LANES];
                    let mut maxi = [0i32; MAX_LANES];
                    for i in 0..n {
                        let b = &v.flat.bands[bands[i]];
                        base[i] = b.base as i32;
                        scale[i] = b.scale;
                        offset[i] = b.offset;
                        last[i] = b.last;
                        maxi[i] = b.len as i32 - 2;
                    }
                    (
                        V::load_i(base.as_ptr()),
                        V::load_f(scale.as_ptr()),
                        V::load_f(offset.as_ptr()),
                        V::load_f(last.as_ptr()),
                        V::load_i(maxi.as_ptr()),
                    )
                };
                // Trilinear, as `trilinear_at`: coordinates are in [0, p − 1), so every
                // tap index is below off + p³ (and 8-bit pair reads stay within the pool's
                // padding).
                let xi = V::to_i(x);
                let yi = V::to_i(y);
                let zi = V::to_i(z);
                let fx = V::sub_f(x, V::to_f(xi));
                let fy = V::sub_f(y, V::to_f(yi));
                let fz = V::sub_f(z, V::to_f(zi));
                let vp = V::splat_i(p as i32);
                let idx = V::add_i(
                    offs,
                    V::add_i(V::mul_i(V::add_i(V::mul_i(zi, vp), yi), vp), xi),
                );
                let ptr = data.as_ptr();
                macro_rules! row {
                    ($d:expr) => {{
                        let (a, b) = T::pair(ptr, V::add_i(idx, V::splat_i($d)));
                        lerp::<V>(a, b, fx)
                    }};
                }
                let c00 = row!(0);
                let c10 = row!(sy);
                let c01 = row!(sz);
                let c11 = row!(sz + sy);
                let c0 = lerp::<V>(c00, c10, fy);
                let c1 = lerp::<V>(c01, c11, fy);
                let s = lerp::<V>(c0, c1, fz);
                // A NaN sample (no data) is transparent: masked off, after an in-bounds
                // lookup (max_f returns its second operand for NaN).
                let valid = V::and_m(mask, V::ord(s, s));
                // Lookup, as `StepTable::lookup`.
                let pos = V::add_f(V::mul_f(s, scale), offset);
                let pos = V::min_f(V::max_f(pos, zero), last);
                let e = V::min_i(V::to_i(pos), maxi);
                let fe = V::sub_f(pos, V::to_f(e));
                // Entries e and e + 1 of the lane's band (e ≤ len − 2, so e + 1 is in the
                // band's table) are eight consecutive floats.
                let mut ei = [0i32; MAX_LANES];
                V::store_i(ei.as_mut_ptr(), V::shl2(V::add_i(e, base)));
                let (lo, hi) = V::lut(lut, &ei);
                macro_rules! ch {
                    ($c:expr) => {
                        V::keep_f(lerp::<V>(lo[$c], hi[$c], fe), valid)
                    };
                }
                let (sr, sg, sb, sa) = (ch!(0), ch!(1), ch!(2), ch!(3));
                // Blend, as `blend`: masked lanes add t·0 and keep their value exactly.
                let t = V::sub_f(one, aa);
                ar = V::add_f(ar, V::mul_f(t, sr));
                ag = V::add_f(ag, V::mul_f(t, sg));
                ab = V::add_f(ab, V::mul_f(t, sb));
                aa = V::add_f(aa, V::mul_f(t, sa));
                let done = V::bits(V::and_m(valid, V::ge(aa, ert)));
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
            V::store_f(acc[0].as_mut_ptr(), ar);
            V::store_f(acc[1].as_mut_ptr(), ag);
            V::store_f(acc[2].as_mut_ptr(), ab);
            V::store_f(acc[3].as_mut_ptr(), aa);
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
