//! One frame of ray casting over a region: volumes and horizons together.
//!
//! Per ray: clip to the region's half-open `t` interval, collect horizon crossings in it,
//! then march the volumes front to back, compositing each surface when the march reaches
//! it (seed 000 §4.3), until the ray leaves the region or is opaque. Where several volumes
//! overlap, the ray is cut at their box boundaries into fragments (the 1D trace of the BSP
//! over their boxes, seed 002); in a fragment every active volume is classified at each
//! sample, the results are mixed, and the mix is composited once.
//!
//! The code is specialised to the frame's effect set ([`strata_common::effects`]): the ray
//! loop is compiled once per set of volume, horizon, lighting and slice effects (`const R`),
//! the sample loop once per set of shading and pre-integration (`const S`), and a frame runs
//! the copy its [`Variant`] names. With no horizons no intersection code is compiled in,
//! with one volume no mixing, without gradient shading no gradient. The general path
//! (`render.variant = "general"`) runs the copy with every effect in, deciding at run time.

use crate::atlas::{Samples, Voxel};
use crate::horizon::{Hit, HorFrame};
use crate::volume::{first_k, first_k_near, trilinear_at, Cursor, VolFrame, NO_LIGHT};
use rayon::prelude::*;
use strata_common::effects::{EffectSet, Variant};
use strata_common::image::{PartialImage, Rect, Rgba};
use strata_common::occlusion::RayLimits;
use strata_common::tf::PreintTable;

/// Tile edge in pixels (rayon's unit of work; one feedback list per tile).
pub const TILE: u32 = 16;

/// Sampling bands: band `b` covers `t` in `[start[b], start[b+1])` with step `dt[b]`.
#[derive(Clone, Debug)]
pub struct Bands {
    /// Start distance of each band (`start[0] = 0`).
    pub start: Vec<f32>,
    /// Step of each band (`base · 2^b`).
    pub dt: Vec<f32>,
}

impl Bands {
    /// The band that distance `t` lies in: the last whose start is at or before `t` (band 0
    /// before the first start, and for NaN).
    #[inline]
    pub fn at(&self, t: f32) -> usize {
        let mut band = 0;
        while band + 1 < self.start.len() && t >= self.start[band + 1] {
            band += 1;
        }
        band
    }
}

/// Everything a frame's rays read.
pub struct FrameSetup<'a> {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Ray direction through pixel corner (0, 0), per column, per row.
    pub dir00: [f32; 3],
    /// Per column.
    pub du: [f32; 3],
    /// Per row.
    pub dv: [f32; 3],
    /// Where image pixels lie on the plane of `dir00`, `du`, `dv` (a wall's tiles).
    pub tiles: strata_common::wall::TileMap,
    /// Region box, camera-relative display space.
    pub region_lo: [f32; 3],
    /// Upper corner.
    pub region_hi: [f32; 3],
    /// Pixels that can see the region.
    pub rect: Rect,
    /// Volumes.
    pub vols: Vec<VolFrame<'a>>,
    /// Horizons.
    pub hors: Vec<HorFrame<'a>>,
    /// Sampling bands.
    pub bands: Bands,
    /// Early ray termination threshold.
    pub ert: f32,
    /// Gradient shading of volumes.
    pub volume_shading: bool,
    /// Only the tiles marked here are cast (row-major over `rect`, [`TILE`]² pixels each);
    /// the others' pixels stay transparent and they ask for nothing. `None`: every tile.
    pub only_tiles: Option<&'a [bool]>,
    /// Called with each tile's requests as soon as the tile is cast, so that the pages it
    /// lacks start loading while the other tiles are still being cast.
    pub on_tile: Option<&'a (dyn Fn(&[crate::feedback::FeedbackEntry]) + Sync)>,
    /// Time each tile with its thread's CPU clock too ([`TileOut::cpu_seconds`]).
    pub cpu_clock: bool,
    /// Depth of the lockstep chunks a tile's rays are marched in (camera-relative units).
    pub chunk: f32,
    /// March single-volume spans in SIMD packets ([`crate::packet`]); only set where the
    /// CPU has AVX2, there is one volume and no gradient shading.
    pub packets: bool,
    /// Lanes per packet (8 or 16, [`crate::packet::lanes_for`]) where `packets` is set.
    pub lanes: usize,
    /// Cross-worker occlusion ([`strata_common::occlusion`]): per screen block, each ray's
    /// termination threshold from what lies in front, or not cast at all (left
    /// transparent, asking for no page). `None`: every ray of the rectangle, with `ert`.
    pub limits: Option<RayLimits<'a>>,
    /// The frame's effects and the code path that renders them.
    pub variant: Variant,
    /// Accumulate each ray's colour in f64 (`render.f64_accumulation`): on the general
    /// path, without packets.
    pub f64_accumulation: bool,
}

/// Bits of the ray loop's effects (`const R`).
const RAY_EFFECTS: u8 = EffectSet::VOLUME.bits()
    | EffectSet::VOLUMES.bits()
    | EffectSet::HORIZONS.bits()
    | EffectSet::LIGHTING.bits()
    | EffectSet::SLICES.bits();
/// Bits of the sample loop's effects (`const S`).
const SAMPLE_EFFECTS: u8 = EffectSet::SHADING.bits() | EffectSet::PREINTEGRATED.bits();
const VOLUME: u8 = EffectSet::VOLUME.bits();
const VOLUMES: u8 = EffectSet::VOLUMES.bits();
const HORIZONS: u8 = EffectSet::HORIZONS.bits();
const LIGHTING: u8 = EffectSet::LIGHTING.bits();
const SLICES: u8 = EffectSet::SLICES.bits();
const SHADING: u8 = EffectSet::SHADING.bits();
const PRE: u8 = EffectSet::PREINTEGRATED.bits();

/// How many of a frame's `n` volumes the code for ray effects `R` marches: none without
/// the volume effect, and none of several without the several-volumes effect (the frame's
/// effects include it whenever one of several is marched, so code without it only meets
/// several volumes that show nothing).
#[inline(always)]
const fn marched_volumes<const R: u8>(n: usize) -> usize {
    if !has(R, VOLUME) || (n > 1 && !has(R, VOLUMES)) {
        0
    } else {
        n
    }
}

/// Whether the code compiled for effect bits `code` includes effect `e`.
#[inline(always)]
const fn has(code: u8, e: u8) -> bool {
    code & e != 0
}

/// Counters of one frame.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CastStats {
    /// Rays cast (pixels inside the region's screen rectangle).
    pub rays: u64,
    /// Trilinear samples taken.
    pub samples: u64,
    /// Lattice samples skipped as empty space.
    pub skipped: u64,
    /// Horizon hits composited.
    pub hits: u64,
    /// Rays ended by early termination.
    pub terminated: u64,
}

impl std::ops::AddAssign for CastStats {
    fn add_assign(&mut self, o: Self) {
        self.rays += o.rays;
        self.samples += o.samples;
        self.skipped += o.skipped;
        self.hits += o.hits;
        self.terminated += o.terminated;
    }
}

/// A rendered frame part.
pub struct CastOutput {
    /// The premultiplied image.
    pub image: PartialImage,
    /// Each tile's feedback (reduced) and counters, tiles in row-major order over the
    /// rectangle; a tile left out by [`FrameSetup::only_tiles`], or with no ray to cast
    /// under [`FrameSetup::limits`], has none (and took no time).
    pub tiles: Vec<TileOut>,
    /// Counters, summed over the tiles cast.
    pub stats: CastStats,
}

/// What one tile of a cast gave besides its pixels.
#[derive(Clone, Debug, Default)]
pub struct TileOut {
    /// The pages its rays asked for (reduced).
    pub feedback: Vec<crate::feedback::FeedbackEntry>,
    /// Its counters.
    pub stats: CastStats,
    /// Seconds its thread spent casting it (wall clock).
    pub seconds: f64,
    /// CPU seconds its thread spent casting it ([`thread_cpu_seconds`], with
    /// [`FrameSetup::cpu_clock`]; else 0, as where the system has no per-thread clock).
    /// Unlike `seconds`, time the thread was descheduled does not count, so more workers
    /// than cores do not inflate it.
    pub cpu_seconds: f64,
}

/// The CPU time the calling thread has used, in seconds (`CLOCK_THREAD_CPUTIME_ID`), or
/// `None` where the system does not say.
pub fn thread_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `clock_gettime` writes the struct it is given and nothing else.
        if unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) } == 0 {
            return Some(ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9);
        }
    }
    None
}

/// The colour a ray accumulates front to back: `Rgba` (f32), as every frame, or `[f64; 4]`
/// (`render.f64_accumulation`, the accuracy study's reference), where the rounding of
/// many blend steps does not grow with the number of samples. Samples and their colours
/// stay f32 either way: each enters the sum once, so their rounding does not accumulate.
pub trait Accum: Copy + Send + Sync + 'static {
    /// Nothing yet.
    const ZERO: Self;
    /// Composites `s` (premultiplied) behind what is there: `acc += (1 − αacc)·s`.
    fn blend(&mut self, s: Rgba);
    /// Whether the opacity reached the termination threshold `ert`.
    fn reached(&self, ert: f32) -> bool;
    /// The colour, rounded to f32.
    fn rgba(&self) -> Rgba;
    /// The rays as f32 rays, for the SIMD packets (which accumulate in f32), if they are.
    fn as_f32<'x, 's, 'a>(
        rays: &'x mut [RayState<'s, 'a, Self>],
    ) -> Option<&'x mut [RayState<'s, 'a, Rgba>]>;
}

impl Accum for Rgba {
    const ZERO: Self = [0.0; 4];

    #[inline(always)]
    fn blend(&mut self, s: Rgba) {
        let t = 1.0 - self[3];
        self[0] += t * s[0];
        self[1] += t * s[1];
        self[2] += t * s[2];
        self[3] += t * s[3];
    }

    #[inline(always)]
    fn reached(&self, ert: f32) -> bool {
        self[3] >= ert
    }

    #[inline(always)]
    fn rgba(&self) -> Rgba {
        *self
    }

    fn as_f32<'x, 's, 'a>(
        rays: &'x mut [RayState<'s, 'a, Self>],
    ) -> Option<&'x mut [RayState<'s, 'a, Rgba>]> {
        Some(rays)
    }
}

impl Accum for [f64; 4] {
    const ZERO: Self = [0.0; 4];

    #[inline(always)]
    fn blend(&mut self, s: Rgba) {
        let t = 1.0 - self[3];
        for (a, c) in self.iter_mut().zip(s) {
            *a += t * c as f64;
        }
    }

    #[inline(always)]
    fn reached(&self, ert: f32) -> bool {
        self[3] >= ert as f64
    }

    #[inline(always)]
    fn rgba(&self) -> Rgba {
        self.map(|v| v as f32)
    }

    fn as_f32<'x, 's, 'a>(
        _: &'x mut [RayState<'s, 'a, Self>],
    ) -> Option<&'x mut [RayState<'s, 'a, Rgba>]> {
        None
    }
}

/// Half-open `[t0, t1)` of the ray inside the region box (origin is the eye at 0).
pub fn clip_region(lo: [f32; 3], hi: [f32; 3], d: [f32; 3]) -> (f32, f32) {
    let mut t0 = 0.0f32;
    let mut t1 = f32::INFINITY;
    for a in 0..3 {
        if d[a] == 0.0 {
            // Parallel to both planes: inside iff the eye is (half-open on the upper side).
            if !(lo[a] <= 0.0 && 0.0 < hi[a]) {
                return (0.0, 0.0);
            }
        } else {
            let ta = lo[a] / d[a];
            let tb = hi[a] / d[a];
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    (t0, t1)
}

/// The band of the segment a span ending at `t` cuts: the band of the first lattice point at
/// or after `t` (the sample that would follow the span's last). The segment from one band's
/// last sample to the next band's first is one step of the next band (`band_start`), so a
/// span ending anywhere on it (a surface, another volume, a region's face) ends with half of
/// that coarse segment, whichever side of the band's start it ends on, as the whole ray's
/// segment and the next region's lead do ([`end_span`]).
fn segment_band(bands: &Bands, t: f32) -> usize {
    let mut band = bands.at(t);
    while band + 1 < bands.start.len() {
        let dt = bands.dt[band];
        let next = (first_k(t.max(bands.start[band]), dt) as f32) * dt;
        if next < bands.start[band + 1] {
            break;
        }
        band += 1;
    }
    band
}

struct RayCtx<'s, 'a, A: Accum> {
    f: &'s FrameSetup<'a>,
    d: [f32; 3],
    acc: A,
    stats: CastStats,
    done: bool,
    /// This ray's termination threshold (the frame's, or lower under occlusion).
    ert: f32,
}

impl<'s, 'a, A: Accum> RayCtx<'s, 'a, A> {
    /// Ends volume `v`'s pre-integrated span at `t` (a surface, or where the volume begins
    /// to overlap another, whose mix is post-classified): the half step after its last
    /// sample joins the ray, and the next sample starts a new span.
    fn end_pre_span(&mut self, v: &VolFrame<'a>, cur: &mut Cursor, t: f32) {
        let Some(pre) = v.pre.as_ref() else { return };
        if cur.prev.is_nan() || self.done {
            return;
        }
        end_span(
            Some(pre),
            segment_band(&self.f.bands, t),
            cur,
            &mut self.acc,
            false,
        );
    }

    /// Marches one volume over `[ta, tb)` on the lattice.
    fn march_one(
        &mut self,
        v: &VolFrame<'a>,
        cur: &mut Cursor,
        md: [f32; 3],
        ta: f32,
        tb: f32,
        fb: &mut crate::feedback::Requests,
    ) {
        // One copy of the loop per sample effect set, per element type of the pool.
        match self.f.variant.compiled.bits() & SAMPLE_EFFECTS {
            0 => self.march_pool::<0>(v, cur, md, ta, tb, fb),
            SHADING => self.march_pool::<SHADING>(v, cur, md, ta, tb, fb),
            PRE => self.march_pool::<PRE>(v, cur, md, ta, tb, fb),
            _ => self.march_pool::<SAMPLE_EFFECTS>(v, cur, md, ta, tb, fb),
        }
    }

    #[inline(always)]
    fn march_pool<const S: u8>(
        &mut self,
        v: &VolFrame<'a>,
        cur: &mut Cursor,
        md: [f32; 3],
        ta: f32,
        tb: f32,
        fb: &mut crate::feedback::Requests,
    ) {
        match v.samples {
            Samples::F32(d) => self.march_typed::<_, S>(v, d, cur, md, ta, tb, fb),
            Samples::U8(d) => self.march_typed::<_, S>(v, d, cur, md, ta, tb, fb),
            Samples::I8(d) => self.march_typed::<_, S>(v, d, cur, md, ta, tb, fb),
            Samples::U16(d) => self.march_typed::<_, S>(v, d, cur, md, ta, tb, fb),
            Samples::I16(d) => self.march_typed::<_, S>(v, d, cur, md, ta, tb, fb),
        }
    }

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn march_typed<T: Voxel, const S: u8>(
        &mut self,
        v: &VolFrame<'a>,
        data: &[T],
        cur: &mut Cursor,
        md: [f32; 3],
        ta: f32,
        tb: f32,
        fb: &mut crate::feedback::Requests,
    ) {
        let f = self.f;
        let bands = &f.bands;
        let mut band = bands.at(ta);
        // Without macrocells no sample ever reaches the cell test.
        let no_cell = if v.cells.is_some() {
            f32::NEG_INFINITY
        } else {
            f32::INFINITY
        };
        let p = v.page;
        let inv = md.map(|m| 1.0 / m);
        let oct = crate::volume::octant(md);
        let mut t_start = ta;
        while t_start < tb && !self.done {
            let dt = bands.dt[band];
            let band_end = bands.start.get(band + 1).copied().unwrap_or(f32::INFINITY);
            let seg_end = tb.min(band_end);
            let table = &v.tables[band];
            let pres = if has(S, PRE) { v.pre.as_deref() } else { None };
            let pre = pres.map(|p| &*p[band]);
            let mut k = first_k(t_start, dt);
            let inv_dt = 1.0 / dt;
            // Hot loop: accumulate in locals, write back once.
            let mut acc = self.acc;
            let mut samples = 0u64;
            let mut skipped = 0u64;
            let ert = self.ert;
            let shading = has(S, SHADING) && f.volume_shading;
            let mut terminated = false;
            // Samples before `cell_exit` lie in a macrocell already found visible.
            let mut cell_exit = no_cell;
            loop {
                let t = k as f32 * dt;
                if t >= seg_end {
                    break;
                }
                if t >= cur.t_exit {
                    let q = v.point(t, md);
                    v.locate(cur, t, q, md, fb);
                    cell_exit = no_cell;
                }
                if cur.transparent {
                    // Jump to the first lattice point past the brick, or past the cube of
                    // transparent bricks it starts (`VolFrame::transparent_runs`); the
                    // cursor stays valid across segments, so a later segment may start
                    // inside it.
                    let nk = first_k_near(cur.t_exit.min(seg_end), dt, inv_dt).max(k + 1);
                    skipped += (nk - k) as u64;
                    k = nk;
                    end_span(pres, band, cur, &mut acc, true);
                    continue;
                }
                let q = v.point(t, md);
                let l = v.local(cur, q);
                // Pre-integration crosses an invisible cell instead of skipping it: its
                // first and last lattice points are sampled, so the segments into and out
                // of it come from real values as without cells (and as on the GPU, which
                // has none), and only the segments between two values of the cell's range,
                // which are clear, are left out.
                let mut cross_to = None;
                if t >= cell_exit {
                    // Without pre-integration a run of invisible cells is one jump.
                    let (visible, exit) = if pre.is_none() {
                        v.cell_run_at(cur, l, md, inv, oct)
                    } else {
                        v.cell_at(cur, l, md, inv)
                    };
                    if !visible {
                        let nk =
                            first_k_near(exit.min(cur.t_exit).min(seg_end), dt, inv_dt).max(k + 1);
                        if pre.is_none() {
                            skipped += (nk - k) as u64;
                            k = nk;
                            continue;
                        }
                        if nk - k >= 3 {
                            cross_to = Some(nk - 1);
                        }
                    } else {
                        cell_exit = exit;
                    }
                }
                // SAFETY: `locate` checked that the cursor's slot lies inside the pool, and
                // `local` clamps to [0, p − 1).
                let s = unsafe { trilinear_at(data, cur.off, p, l) };
                samples += 1;
                k += 1;
                if s.is_nan() {
                    end_span(pres, band, cur, &mut acc, false);
                    continue; // no data: transparent
                }
                if let (true, Some(pre)) = (has(S, PRE), pre) {
                    let light = if shading {
                        light(v, cur, q, self.d)
                    } else {
                        NO_LIGHT
                    };
                    if cur.prev.is_nan() {
                        // A span's first sample: the half step before it waits for the
                        // next sample, which gives the slope to extrapolate it with. Should
                        // none come (a one-sample span), the value's change along the ray
                        // over a step, by central differences half a voxel either side,
                        // stands in for it.
                        cur.lead = true;
                        if !cur.entered {
                            // The ray's first sample of this volume in this region: were the
                            // lattice point before it inside the volume and hidden, an
                            // undivided region would have skipped it, and this span's lead
                            // is a whole step whichever region the point lies in.
                            cur.entered = true;
                            // (Whatever `skipping` says: without it, a brick of no data
                            // is still skipped, and the bits `hidden_at` reads say so.)
                            let tp = t - dt;
                            if !cur.gap && tp >= cur.vol_start {
                                let qp = v.point(tp, md);
                                cur.gap = v.hidden_at(tp, qp);
                            }
                        }
                        let e = slope_eps(md);
                        let [qa, qb] =
                            [-e, e].map(|o| [q[0] + o * md[0], q[1] + o * md[1], q[2] + o * md[2]]);
                        // SAFETY: as for `s` (`local` clamps into the slot).
                        let (sa, sb) = unsafe {
                            (
                                trilinear_at(data, cur.off, p, v.local(cur, qa)),
                                trilinear_at(data, cur.off, p, v.local(cur, qb)),
                            )
                        };
                        // One-sided where a tap falls on no data (the edge of a no-data
                        // region): a value linear up to it is still extrapolated exactly.
                        let slope = if sa.is_nan() {
                            (sb - s) / e * dt
                        } else if sb.is_nan() {
                            (s - sa) / e * dt
                        } else {
                            (sb - sa) / (2.0 * e) * dt
                        };
                        cur.slope = if slope.is_finite() { slope } else { 0.0 };
                    } else {
                        if cur.lead {
                            // The half step before the span's first sample (a whole step
                            // after skipped empty space), the value extrapolated linearly
                            // to its front.
                            // In the first sample's own band: a band's last sample
                            // followed by the next band's first is a coarse step away, and
                            // its lead is a step of its own band, by the value's change
                            // over that step.
                            let own = cur.prev_band as usize;
                            let mut rgba = if own == band {
                                if cur.gap {
                                    pre.lookup(2.0 * cur.prev - s, cur.prev)
                                } else {
                                    pre.lookup_half(1.5 * cur.prev - 0.5 * s, cur.prev)
                                }
                            } else {
                                let lt = &*pres.expect("pre-integrated")[own];
                                let r = (1u32 << (band - own).min(16)) as f32;
                                let g = (s - cur.prev) / r;
                                if cur.gap {
                                    lt.lookup(cur.prev - g, cur.prev)
                                } else {
                                    lt.lookup_half(cur.prev - 0.5 * g, cur.prev)
                                }
                            };
                            apply_light(&mut rgba, cur.prev_light);
                            acc.blend(rgba);
                            cur.lead = false;
                            cur.gap = false;
                        }
                        // The segment from the previous sample.
                        let mut rgba = pre.lookup(cur.prev, s);
                        apply_light(&mut rgba, light);
                        acc.blend(rgba);
                    }
                    cur.before = cur.prev;
                    cur.prev = s;
                    cur.prev_band = band as u8;
                    cur.prev_light = light;
                    if acc.reached(ert) {
                        terminated = true;
                        break;
                    }
                    if let Some(j) = cross_to {
                        // On to the cell's last lattice point (same brick and band).
                        let tj = j as f32 * dt;
                        let qj = v.point(tj, md);
                        // SAFETY: as for `s`.
                        let sj = unsafe { trilinear_at(data, cur.off, p, v.local(cur, qj)) };
                        samples += 1;
                        skipped += (j - k) as u64;
                        k = j + 1;
                        if sj.is_nan() {
                            end_span(pres, band, cur, &mut acc, false);
                            continue;
                        }
                        // Steps from `s` to `sj`: the value's slope across the cell.
                        let g = (sj - s) / (tj - t) * dt;
                        if cur.lead {
                            let mut rgba = if cur.gap {
                                pre.lookup(s - g, s)
                            } else {
                                pre.lookup_half(s - 0.5 * g, s)
                            };
                            apply_light(&mut rgba, light);
                            acc.blend(rgba);
                            cur.lead = false;
                            cur.gap = false;
                        }
                        cur.before = sj - g;
                        cur.prev = sj;
                        cur.prev_band = band as u8;
                        cur.prev_light = if shading {
                            self::light(v, cur, qj, self.d)
                        } else {
                            NO_LIGHT
                        };
                    }
                    continue;
                }
                let mut rgba = table.lookup(s);
                if shading {
                    if rgba[3] <= 0.0 {
                        continue; // no gradient for what does not show
                    }
                    apply_light(&mut rgba, light(v, cur, q, self.d));
                }
                // Unconditionally: a zero-opacity entry is all zeros (premultiplied), so the
                // blend leaves `acc` exactly as it is, and a data-dependent branch costs more
                // than the arithmetic.
                acc.blend(rgba);
                if acc.reached(ert) {
                    terminated = true;
                    break;
                }
            }
            // The ray leaves the volume: its span ends half a step after its last sample.
            if has(S, PRE) && !terminated && seg_end >= cur.span_end {
                // Past the region, were the next lattice point inside the volume and hidden,
                // an undivided region would skip it: the span ends with a whole step.
                // It cuts the segment to the lattice point that would follow (the next
                // band's first past this band's last sample): half a step of its band.
                let seg = segment_band(bands, cur.span_end);
                let tn = first_k(cur.span_end.max(bands.start[seg]), bands.dt[seg]) as f32
                    * bands.dt[seg];
                let skip = !cur.prev.is_nan() && tn < cur.vol_end && {
                    let qn = v.point(tn, md);
                    v.hidden_at(tn, qn)
                };
                end_span(pres, seg, cur, &mut acc, skip);
            }
            self.acc = acc;
            self.stats.samples += samples;
            self.stats.skipped += skipped;
            if terminated {
                self.done = true;
                self.stats.terminated += 1;
                return;
            }
            t_start = seg_end;
            band += 1;
        }
    }

    /// Marches several overlapping volumes over `[ta, tb)`: classify each, mix, composite.
    #[allow(clippy::too_many_arguments)]
    fn march_mixed<const S: u8>(
        &mut self,
        active: &[usize],
        curs: &mut [Cursor],
        mds: &[[f32; 3]],
        ta: f32,
        tb: f32,
        fb: &mut crate::feedback::Requests,
    ) {
        let f = self.f;
        let bands = &f.bands;
        let mut band = bands.at(ta);
        let mut t_start = ta;
        while t_start < tb && !self.done {
            let dt = bands.dt[band];
            let band_end = bands.start.get(band + 1).copied().unwrap_or(f32::INFINITY);
            let seg_end = tb.min(band_end);
            let mut k = first_k(t_start, dt);
            loop {
                let t = k as f32 * dt;
                if t >= seg_end {
                    break;
                }
                k += 1;
                let mut sum = [0.0f32; 3];
                let mut alpha_sum = 0.0f32;
                let mut transmit = 1.0f32;
                for &vi in active {
                    let v = &f.vols[vi];
                    let md = mds[vi];
                    let cur = &mut curs[vi];
                    let q = v.point(t, md);
                    if t >= cur.t_exit {
                        v.locate(cur, t, q, md, fb);
                    }
                    if cur.transparent {
                        continue;
                    }
                    let s = v.sample(cur, q);
                    self.stats.samples += 1;
                    if s.is_nan() {
                        continue;
                    }
                    let mut rgba = v.tables[band].lookup(s);
                    if rgba[3] <= 0.0 {
                        continue;
                    }
                    if has(S, SHADING) && f.volume_shading {
                        shade(v, cur, q, self.d, &mut rgba);
                    }
                    sum[0] += rgba[0];
                    sum[1] += rgba[1];
                    sum[2] += rgba[2];
                    alpha_sum += rgba[3];
                    transmit *= 1.0 - rgba[3];
                }
                if alpha_sum <= 0.0 {
                    continue;
                }
                // Opacities combine as independent absorbers; colours mix weighted by
                // opacity (the premultiplied sums, renormalised to the combined alpha).
                let a = 1.0 - transmit;
                let w = a / alpha_sum;
                self.acc.blend([sum[0] * w, sum[1] * w, sum[2] * w, a]);
                if self.acc.reached(self.ert) {
                    self.done = true;
                    self.stats.terminated += 1;
                    return;
                }
            }
            t_start = seg_end;
            band += 1;
        }
    }
}

/// Ends a span of samples (empty space, no data, or the volume's end follows). With
/// pre-integration the half step after its last sample joins the ray, the value
/// extrapolated linearly to its back from the sample before (a one-sample span: the
/// sample's whole step, classified alone), lit as that sample was: a span covers half a
/// step before its first sample and after its last, as point samples would, and a value
/// linear along the ray is integrated exactly. Where skipped empty space follows (`skip`:
/// a brick or macrocell whose values the transfer function hides) the span covers the
/// whole step to the next lattice point instead, and the next span the whole step before
/// its first sample (`Cursor::gap`): the segment between a hidden sample and a visible one
/// can cross opacity that neither sample shows (a thin peak of the transfer function
/// between the two values), and the extrapolation integrates it exactly for a linear
/// value. A one-sample span has no neighbour to extrapolate from: its value's slope along
/// the ray (`Cursor::slope`) stands in. The cursor then has no sample before the next.
///
/// `seg` is the band of the segment after the last sample (the band of the lattice point
/// that would follow it): past a band's last sample it is the next band, whose step is
/// `2^(seg − prev_band)` of the sample's own, and the half step after is half of it,
/// extrapolated that far. The lead of a one-sample span is its own band's.
#[inline(always)]
fn end_span<A: Accum>(
    pres: Option<&[std::sync::Arc<PreintTable>]>,
    seg: usize,
    cur: &mut Cursor,
    acc: &mut A,
    skip: bool,
) {
    if let Some(pres) = pres {
        let p = cur.prev;
        if !p.is_nan() {
            let own = cur.prev_band as usize;
            let (lead_table, pre) = (&*pres[own], &*pres[seg]);
            // The segment's step in steps of the sample's own band.
            let ratio = (1u32 << seg.saturating_sub(own).min(16)) as f32;
            // The value half a step and a step of the segment past the last sample.
            let (half, whole) = if cur.lead {
                // A one-sample span: the step before it too, both by its slope.
                let g = cur.slope;
                let mut rgba = if cur.gap {
                    lead_table.lookup(p - g, p)
                } else {
                    lead_table.lookup_half(p - 0.5 * g, p)
                };
                apply_light(&mut rgba, cur.prev_light);
                acc.blend(rgba);
                if ratio == 1.0 {
                    (p + 0.5 * g, p + g)
                } else {
                    (p + 0.5 * ratio * g, p + ratio * g)
                }
            } else if ratio == 1.0 {
                (1.5 * p - 0.5 * cur.before, 2.0 * p - cur.before)
            } else {
                let g = p - cur.before;
                (p + 0.5 * ratio * g, p + ratio * g)
            };
            let mut rgba = if skip {
                pre.lookup(p, whole)
            } else {
                pre.lookup_half(p, half)
            };
            apply_light(&mut rgba, cur.prev_light);
            acc.blend(rgba);
        }
    }
    cur.prev = f32::NAN;
    cur.before = f32::NAN;
    cur.lead = false;
    cur.gap = skip;
}

/// The ray distance that moves a sample half a level-0 voxel along its largest index axis
/// (a one-sample span's slope is taken over twice that).
#[inline(always)]
fn slope_eps(md: [f32; 3]) -> f32 {
    0.5 / md[0].abs().max(md[1].abs()).max(md[2].abs())
}

fn shade(v: &VolFrame<'_>, cur: &Cursor, q: [f32; 3], d: [f32; 3], rgba: &mut Rgba) {
    apply_light(rgba, light(v, cur, q, d));
}

/// Headlight Blinn-Phong factors at `q`: `[ambient + diffuse, specular per unit of
/// opacity]`, or [`NO_LIGHT`] where the gradient vanishes.
fn light(v: &VolFrame<'_>, cur: &Cursor, q: [f32; 3], d: [f32; 3]) -> [f32; 2] {
    let g = v.gradient(cur, q);
    // Index-space gradient to camera space: ∇_world = Mᵀ ∇_index.
    let m = &v.m;
    let n = [
        m[0][0] * g[0] + m[1][0] * g[1] + m[2][0] * g[2],
        m[0][1] * g[0] + m[1][1] * g[1] + m[2][1] * g[2],
        m[0][2] * g[0] + m[1][2] * g[1] + m[2][2] * g[2],
    ];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if !(len > 1e-12) || !len.is_finite() {
        return NO_LIGHT;
    }
    let cosv = ((n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / len).abs();
    // Ambient + diffuse + a little specular.
    [0.3 + 0.6 * cosv, 0.25 * cosv.powi(24)]
}

/// Lights a premultiplied colour with [`light`]'s factors.
#[inline(always)]
fn apply_light(rgba: &mut Rgba, l: [f32; 2]) {
    let spec = l[1] * rgba[3];
    for c in rgba.iter_mut().take(3) {
        *c = *c * l[0] + spec;
    }
}

/// A ray in flight: everything needed to continue marching it later. Tiles march their
/// rays in lockstep chunks of `t` so that neighbouring rays touch the same bricks while
/// they are in cache; because samples sit on the global lattice, where a march is cut
/// into chunks changes nothing.
pub struct RayState<'s, 'a, A: Accum = Rgba> {
    ctx: RayCtx<'s, 'a, A>,
    t1: f32,
    cur_t: f32,
    hits: Vec<Hit>,
    hi: usize,
    md0: [f32; 3],
    span0: (f32, f32),
    single: Cursor,
    mds: Vec<[f32; 3]>,
    spans: Vec<(f32, f32)>,
    curs: Vec<Cursor>,
}

impl<'s, 'a, A: Accum> RayState<'s, 'a, A> {
    /// Whether the ray needs more marching.
    pub fn active(&self) -> bool {
        !self.ctx.done && self.cur_t < self.t1
    }

    /// The volume interval `advance(until)` would march first, for a single-volume frame:
    /// `(ta, tb, cur_t after it)`, or `None` if it would march nothing first.
    pub fn pending(&self, until: f32) -> Option<(f32, f32, f32)> {
        if self.ctx.done || self.ctx.f.vols.len() != 1 {
            return None;
        }
        let next_hit = self.hits.get(self.hi).map_or(f32::INFINITY, |h| h.t);
        let seg_end = next_hit.min(self.t1).min(until);
        if seg_end <= self.cur_t {
            return None;
        }
        let (a, b) = self.span0;
        let (a, b) = (a.max(self.cur_t), b.min(seg_end));
        (a < b).then_some((a, b, seg_end))
    }

    /// The ray's termination threshold.
    pub fn ert(&self) -> f32 {
        self.ctx.ert
    }

    /// The ray's index-space direction in its (single) volume.
    pub fn md0(&self) -> [f32; 3] {
        self.md0
    }

    /// The ray's cursor in its (single) volume.
    pub fn cursor(&self) -> &Cursor {
        &self.single
    }

    /// The accumulated premultiplied colour (rounded to f32).
    pub fn acc(&self) -> Rgba {
        self.ctx.acc.rgba()
    }

    /// Marches (volumes and surfaces, front to back) up to `until` (exclusive), with the
    /// general path's code.
    pub fn advance(&mut self, until: f32, fb: &mut crate::feedback::Requests) {
        self.advance_with::<RAY_EFFECTS>(until, fb)
    }

    /// [`advance`](Self::advance) compiled for the ray effects `R` (which hold the frame's).
    #[inline(always)]
    fn advance_with<const R: u8>(&mut self, until: f32, fb: &mut crate::feedback::Requests) {
        let f = self.ctx.f;
        let nv = marched_volumes::<R>(f.vols.len());
        let surfaces = has(R, HORIZONS | SLICES);
        loop {
            if self.ctx.done {
                return;
            }
            let next_hit = if surfaces {
                self.hits.get(self.hi).map_or(f32::INFINITY, |h| h.t)
            } else {
                f32::INFINITY
            };
            let seg_end = next_hit.min(self.t1).min(until);
            if seg_end > self.cur_t {
                match nv {
                    0 => {}
                    1 => {
                        let (a, b) = self.span0;
                        let (a, b) = (a.max(self.cur_t), b.min(seg_end));
                        if a < b {
                            self.ctx
                                .march_one(&f.vols[0], &mut self.single, self.md0, a, b, fb);
                        }
                    }
                    _ if has(R, VOLUMES) => f.march_fragments(
                        &mut self.ctx,
                        &mut self.curs,
                        &self.mds,
                        &self.spans,
                        self.cur_t,
                        seg_end,
                        fb,
                    ),
                    _ => unreachable!("several volumes run only where R has them"),
                }
                self.cur_t = seg_end;
            }
            if self.ctx.done {
                return;
            }
            // The next surface is reached (it lies before `until` and inside the region).
            if surfaces && next_hit < self.t1 && next_hit <= until && seg_end >= next_hit {
                // Pre-integrated spans end at the surface (an opaque one ends the ray).
                match nv {
                    1 => self
                        .ctx
                        .end_pre_span(&f.vols[0], &mut self.single, next_hit),
                    n if n > 1 => {
                        for (v, c) in f.vols.iter().zip(self.curs.iter_mut()) {
                            self.ctx.end_pre_span(v, c, next_hit);
                        }
                    }
                    _ => {}
                }
                let h = self.hits[self.hi];
                self.ctx.acc.blend(h.rgba);
                self.ctx.stats.hits += 1;
                self.hi += 1;
                if self.ctx.acc.reached(self.ctx.ert) {
                    self.ctx.done = true;
                    self.ctx.stats.terminated += 1;
                    return;
                }
                self.cur_t = self.cur_t.max(next_hit);
                continue;
            }
            if seg_end >= self.t1 {
                self.cur_t = self.t1;
            }
            return;
        }
    }
}

impl<'s, 'a> RayState<'s, 'a, Rgba> {
    /// Takes the outcome of a packet's march of the interval [`pending`](Self::pending)
    /// gave: what the scalar march would have left.
    pub fn finish_packet(
        &mut self,
        acc: Rgba,
        cur: Cursor,
        samples: u64,
        skipped: u64,
        terminated: bool,
        then: f32,
    ) {
        self.ctx.acc = acc;
        self.single = cur;
        self.ctx.stats.samples += samples;
        self.ctx.stats.skipped += skipped;
        if terminated {
            self.ctx.done = true;
            self.ctx.stats.terminated += 1;
        }
        self.cur_t = then;
    }
}

impl<'a> FrameSetup<'a> {
    /// Starts a ray: clips it to the region, finds its surface crossings and volume spans.
    pub fn start<'s>(
        &'s self,
        d: [f32; 3],
        fb: &mut crate::feedback::Requests,
    ) -> RayState<'s, 'a> {
        self.start_with(d, fb, Vec::new())
    }

    /// [`start`](Self::start), keeping the ray's surface crossings in `hits` (cleared
    /// first), so a caller can reuse one buffer for many rays. General path.
    pub fn start_with<'s>(
        &'s self,
        d: [f32; 3],
        fb: &mut crate::feedback::Requests,
        hits: Vec<Hit>,
    ) -> RayState<'s, 'a> {
        self.start_r::<RAY_EFFECTS, Rgba>(d, fb, hits)
    }

    /// [`start_with`](Self::start_with) compiled for the ray effects `R`.
    #[inline(always)]
    fn start_r<'s, const R: u8, A: Accum>(
        &'s self,
        d: [f32; 3],
        fb: &mut crate::feedback::Requests,
        mut hits: Vec<Hit>,
    ) -> RayState<'s, 'a, A> {
        hits.clear();
        let (t0, t1) = clip_region(self.region_lo, self.region_hi, d);
        let mut st = RayState {
            ctx: RayCtx {
                f: self,
                d,
                acc: A::ZERO,
                stats: CastStats {
                    rays: 1,
                    ..CastStats::default()
                },
                done: false,
                ert: self.ert,
            },
            t1,
            cur_t: t0,
            hits,
            hi: 0,
            md0: [0.0; 3],
            span0: (0.0, 0.0),
            single: Cursor::default(),
            mds: Vec::new(),
            spans: Vec::new(),
            curs: Vec::new(),
        };
        if t0 >= t1 {
            st.ctx.done = true;
            return st;
        }
        // Slices first, then each horizon searched only up to the nearest opaque surface
        // found so far: what lies behind it is invisible.
        if has(R, SLICES) {
            for v in &self.vols {
                if !v.slices.is_empty() {
                    v.slice_hits(v.index_dir(d), t0, t1, &mut st.hits, fb);
                }
            }
        }
        let mut limit = st
            .hits
            .iter()
            .filter(|h| h.rgba[3] >= 1.0)
            .fold(t1, |m, h| m.min(h.t));
        let hors: &[HorFrame<'a>] = if has(R, HORIZONS) { &self.hors } else { &[] };
        for h in hors {
            let first = st.hits.len();
            limit = limit.min(if has(R, LIGHTING) {
                h.intersect_with::<true>(d, t0, limit, &mut st.hits, fb)
            } else {
                h.intersect_with::<false>(d, t0, limit, &mut st.hits, fb)
            });
            if let Some((vi, no_data)) = h.attribute {
                // The volume's colour where the surface lies (the hit is shaded white).
                for hit in &mut st.hits[first..] {
                    let c = self.vols[vi].color_at(hit.t, d, fb).unwrap_or(no_data);
                    for k in 0..3 {
                        hit.rgba[k] *= c[k];
                    }
                }
            }
        }
        if st.hits.len() > 1 {
            st.hits.sort_by(|a, b| a.t.total_cmp(&b.t));
        }
        let nv = marched_volumes::<R>(self.vols.len());
        // A volume whose transfer function shows nothing is never marched (its slices
        // still show).
        if nv == 1 {
            st.md0 = self.vols[0].index_dir(d);
            let (a, b) = self.vols[0].interval(st.md0);
            st.span0 = if self.vols[0].invisible {
                (0.0, 0.0)
            } else {
                (a.max(t0), b.min(t1))
            };
            st.single.span_end = st.span0.1;
            (st.single.vol_start, st.single.vol_end) = (a, b);
        } else if has(R, VOLUMES) && nv > 1 {
            st.curs.resize_with(nv, Cursor::default);
            for (v, c) in self.vols.iter().zip(st.curs.iter_mut()) {
                let md = v.index_dir(d);
                let (a, b) = v.interval(md);
                st.mds.push(md);
                let span = if v.invisible {
                    (0.0, 0.0)
                } else {
                    (a.max(t0), b.min(t1))
                };
                st.spans.push(span);
                c.span_end = span.1;
                (c.vol_start, c.vol_end) = (a, b);
            }
        }
        st
    }

    /// Casts one ray whole; `fb` collects requested pages.
    pub fn cast(&self, d: [f32; 3], fb: &mut crate::feedback::Requests) -> (Rgba, CastStats) {
        let mut st = self.start(d, fb);
        st.advance(f32::INFINITY, fb);
        (st.ctx.acc, st.ctx.stats)
    }

    /// Cuts `[ta, tb)` at the volumes' box boundaries and marches each fragment with its
    /// active set.
    #[allow(clippy::too_many_arguments)]
    fn march_fragments<'s, A: Accum>(
        &'s self,
        ctx: &mut RayCtx<'s, 'a, A>,
        curs: &mut [Cursor],
        mds: &[[f32; 3]],
        spans: &[(f32, f32)],
        ta: f32,
        tb: f32,
        fb: &mut crate::feedback::Requests,
    ) {
        let mut cuts: Vec<f32> = vec![ta, tb];
        for &(a, b) in spans {
            if a < b {
                for t in [a, b] {
                    if t > ta && t < tb {
                        cuts.push(t);
                    }
                }
            }
        }
        cuts.sort_by(|a, b| a.total_cmp(b));
        cuts.dedup();
        let mut active = Vec::with_capacity(spans.len());
        for w in cuts.windows(2) {
            let (fa, fbnd) = (w[0], w[1]);
            if ctx.done {
                return;
            }
            active.clear();
            for (i, &(a, b)) in spans.iter().enumerate() {
                if a <= fa && fbnd <= b && a < b {
                    active.push(i);
                }
            }
            match active.len() {
                0 => {}
                1 => {
                    let i = active[0];
                    ctx.march_one(&self.vols[i], &mut curs[i], mds[i], fa, fbnd, fb);
                }
                // Shading is the only sample effect of the mix (it stays post-classified):
                // pre-integrated spans end where it begins.
                _ if has(self.variant.compiled.bits(), SHADING) => {
                    for &i in &active {
                        ctx.end_pre_span(&self.vols[i], &mut curs[i], fa);
                    }
                    ctx.march_mixed::<SHADING>(&active, curs, mds, fa, fbnd, fb)
                }
                _ => {
                    for &i in &active {
                        ctx.end_pre_span(&self.vols[i], &mut curs[i], fa);
                    }
                    ctx.march_mixed::<0>(&active, curs, mds, fa, fbnd, fb)
                }
            }
        }
    }

    /// Casts every pixel of the region's rectangle with rayon over tiles; each tile writes
    /// its pixels straight into the image. Runs the copy of the ray loop compiled for the
    /// frame's [`Variant`].
    pub fn render(&self) -> CastOutput {
        if self.f64_accumulation {
            // The accuracy study's reference: one copy, every effect compiled in.
            return self.render_with::<RAY_EFFECTS, [f64; 4]>();
        }
        // Every closed set of ray effects: volumes (none, one, several) × horizons (none,
        // unlit, lit) × slices. A set outside the list (not closed) takes the general path.
        const V1: u8 = VOLUME;
        const V2: u8 = VOLUME | VOLUMES;
        const H1: u8 = HORIZONS;
        const H2: u8 = HORIZONS | LIGHTING;
        const SL: u8 = SLICES;
        macro_rules! one_of {
            ($($v:expr),*) => {
                match self.variant.compiled.bits() & RAY_EFFECTS {
                    $(b if b == $v => self.render_with::<{ $v }, Rgba>(),)*
                    _ => self.render_with::<RAY_EFFECTS, Rgba>(),
                }
            };
        }
        one_of!(
            0,
            V1,
            V2,
            H1,
            V1 | H1,
            V2 | H1,
            H2,
            V1 | H2,
            V2 | H2,
            SL,
            V1 | SL,
            V2 | SL,
            H1 | SL,
            V1 | H1 | SL,
            V2 | H1 | SL,
            H2 | SL,
            V1 | H2 | SL
        )
    }

    fn render_with<const R: u8, A: Accum>(&self) -> CastOutput {
        let r = self.rect;
        let tiles_x = r.w.div_ceil(TILE);
        let tiles_y = r.h.div_ceil(TILE);
        let mut pixels = vec![[0.0f32; 4]; r.area()];
        let out = TileSink(pixels.as_mut_ptr());
        let tiles: Vec<TileOut> = (0..tiles_x * tiles_y)
            .into_par_iter()
            .map(|ti| {
                if self
                    .only_tiles
                    .is_some_and(|o| !o.get(ti as usize).copied().unwrap_or(true))
                {
                    return TileOut::default();
                }
                let tx = r.x + (ti % tiles_x) * TILE;
                let ty = r.y + (ti / tiles_x) * TILE;
                let w = TILE.min(r.x + r.w - tx);
                let h = TILE.min(r.y + r.h - ty);
                let limits = self.limits;
                // A tile with no ray to cast (cross-worker occlusion, a re-cast's blocks)
                // costs nothing and is not timed: the thread clock is a system call (about
                // 0.5 µs here), and a re-cast skips most of a region's tiles.
                if limits.is_some_and(|l| l.none_in(tx, ty, w, h)) {
                    return TileOut::default();
                }
                let t0 = std::time::Instant::now();
                let c0 = if self.cpu_clock {
                    thread_cpu_seconds()
                } else {
                    None
                };
                let done = |feedback: Vec<crate::feedback::FeedbackEntry>, stats| {
                    let seconds = t0.elapsed().as_secs_f64();
                    // (Read again only where it was read at the start: off, no system call.)
                    let cpu_seconds = c0
                        .and_then(|a| thread_cpu_seconds().map(|b| (b - a).max(0.0)))
                        .unwrap_or(0.0);
                    if let Some(f) = self.on_tile {
                        f(&feedback);
                    }
                    TileOut {
                        feedback,
                        stats,
                        seconds,
                        cpu_seconds,
                    }
                };
                let mut fb = crate::feedback::Requests::new();
                let mut st = CastStats::default();
                // The ray's own threshold, or None when it is not cast.
                let ert = |x: u32, y: u32| match limits {
                    Some(l) => l.ray(x, y),
                    None => Some(self.ert),
                };
                if !self.chunk.is_finite() {
                    // Nothing to march in lockstep (surfaces and slices only): each ray whole,
                    // one after the other, reusing one crossing buffer.
                    let mut hits = Vec::new();
                    for y in ty..ty + h {
                        for x in tx..tx + w {
                            let Some(e) = ert(x, y) else { continue };
                            let mut ray = self.start_r::<R, A>(ray_dir(self, x, y), &mut fb, hits);
                            ray.ctx.ert = e;
                            ray.advance_with::<R>(f32::INFINITY, &mut fb);
                            st += ray.ctx.stats;
                            let i = (y - r.y) * r.w + (x - r.x);
                            // SAFETY: (x, y) lies in this tile, inside the rectangle; tiles do
                            // not overlap, and `pixels` outlives the parallel loop.
                            unsafe { out.write(i as usize, sanitize(ray.ctx.acc.rgba())) };
                            hits = std::mem::take(&mut ray.hits);
                        }
                    }
                    return done(crate::feedback::reduce_tile(&mut fb), st);
                }
                let mut rays: Vec<RayState<'_, '_, A>> = Vec::with_capacity((w * h) as usize);
                // Each ray's pixel (within the rectangle), as some may be skipped.
                let mut at: Vec<u32> = Vec::with_capacity((w * h) as usize);
                // Rays in blocks of 4 × (lanes / 4) pixels, so that a packet's rays are
                // neighbours both ways and cross bricks and cells at nearly the same steps
                // (rows of 16 pixels spread a packet four times wider); one block of the
                // tile without packets.
                let (bw, bh) = if self.packets {
                    (4, (self.lanes as u32 / 4).max(1))
                } else {
                    (w, h)
                };
                for by in (ty..ty + h).step_by(bh as usize) {
                    for bx in (tx..tx + w).step_by(bw as usize) {
                        for y in by..(by + bh).min(ty + h) {
                            for x in bx..(bx + bw).min(tx + w) {
                                let Some(e) = ert(x, y) else { continue };
                                let mut ray =
                                    self.start_r::<R, A>(ray_dir(self, x, y), &mut fb, Vec::new());
                                ray.ctx.ert = e;
                                rays.push(ray);
                                at.push((y - r.y) * r.w + (x - r.x));
                            }
                        }
                    }
                }
                // March all rays of the tile chunk by chunk along t.
                let mut c = rays
                    .iter()
                    .filter(|r| r.active())
                    .map(|r| (r.cur_t / self.chunk).floor())
                    .fold(f32::INFINITY, f32::min);
                let mut work = Vec::with_capacity(self.lanes);
                while c.is_finite() {
                    let until = (c + 1.0) * self.chunk;
                    // (f64 accumulation has no packets: `packets` is off then.)
                    if let (true, Some(rays)) = (self.packets, A::as_f32(&mut rays)) {
                        // The chunk's first volume span of every ray, `lanes` rays at a time;
                        // `advance` below then does the rest (surfaces, later spans).
                        for i in 0..rays.len() {
                            let r = &rays[i];
                            if r.active() && r.cur_t < until {
                                if let Some((ta, tb, then)) = r.pending(until) {
                                    work.push(crate::packet::Pending {
                                        ray: i,
                                        ta,
                                        tb,
                                        then,
                                    });
                                }
                            }
                            if work.len() == self.lanes {
                                crate::packet::march(self, rays, &work, &mut fb);
                                work.clear();
                            }
                        }
                        if !work.is_empty() {
                            crate::packet::march(self, rays, &work, &mut fb);
                            work.clear();
                        }
                    }
                    let mut next = f32::INFINITY;
                    for r in rays.iter_mut() {
                        if r.active() && r.cur_t < until {
                            r.advance_with::<R>(until, &mut fb);
                        }
                        if r.active() {
                            next = next.min((r.cur_t / self.chunk).floor());
                        }
                    }
                    c = if next.is_finite() {
                        next.max(c + 1.0)
                    } else {
                        next
                    };
                }
                for (ray, &i) in rays.iter().zip(&at) {
                    st += ray.ctx.stats;
                    // SAFETY: pixel `i` lies in this tile, inside the rectangle, and tiles do
                    // not overlap, so no other thread writes this pixel; `pixels` outlives
                    // the parallel loop.
                    unsafe { out.write(i as usize, sanitize(ray.ctx.acc.rgba())) };
                }
                done(crate::feedback::reduce_tile(&mut fb), st)
            })
            .collect();
        let mut stats = CastStats::default();
        for t in &tiles {
            stats += t.stats;
        }
        CastOutput {
            image: PartialImage {
                width: self.width,
                height: self.height,
                rect: r,
                pixels,
            },
            tiles,
            stats,
        }
    }
}

/// The image's pixels, written by the tiles in parallel (each tile its own pixels).
#[derive(Copy, Clone)]
struct TileSink(*mut Rgba);

// SAFETY: tiles write disjoint pixels (see `render`).
unsafe impl Send for TileSink {}
unsafe impl Sync for TileSink {}

impl TileSink {
    /// # Safety
    /// `i` is inside the image and no other thread writes pixel `i` concurrently.
    #[inline]
    unsafe fn write(self, i: usize, v: Rgba) {
        unsafe { *self.0.add(i) = v };
    }
}

/// Keeps NaN and Inf out of every output pixel, and alpha within [0, 1].
#[inline]
fn sanitize(c: Rgba) -> Rgba {
    if c.iter().all(|v| v.is_finite()) {
        [
            c[0].max(0.0),
            c[1].max(0.0),
            c[2].max(0.0),
            c[3].clamp(0.0, 1.0),
        ]
    } else {
        [0.0; 4]
    }
}

#[inline]
fn ray_dir(f: &FrameSetup<'_>, x: u32, y: u32) -> [f32; 3] {
    let (x, y) = f.tiles.to_plane(x, y);
    let fx = x as f32 + 0.5;
    let fy = y as f32 + 0.5;
    let d = [
        f.dir00[0] + fx * f.du[0] + fy * f.dv[0],
        f.dir00[1] + fx * f.du[1] + fy * f.dv[1],
        f.dir00[2] + fx * f.du[2] + fy * f.dv[2],
    ];
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    d.map(|v| v / l)
}
