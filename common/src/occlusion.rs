//! Cross-worker occlusion: how far a worker need cast its rays, given what the workers in
//! front of its region already make opaque.
//!
//! Early ray termination stops a ray once its accumulated opacity reaches the threshold
//! `t`. In sort-last rendering each worker sees only its own region, so a ray that an opaque
//! horizon or a dense volume in front has already finished is still cast in full by every
//! worker behind, and a ray half-finished in front is marched behind until it is opaque on
//! its own. Here the screen is cut into square blocks of [`BlockGrid::block`] pixels, and:
//!
//! 1. every worker reduces its partial image to a [`Transmittance`] per block (the largest
//!    `1 − α` of the block's pixels, rounded *up* to a multiple of 1/65535, so it never
//!    understates what passes);
//! 2. [`front_of`] multiplies these front to back in the visibility order, giving each
//!    position the [`FrontTransmittance`] of everything in front of it (rounded up again);
//! 3. a ray whose block lets `T` through from the front is cast with the termination
//!    threshold `1 − (1 − t)/T` instead of `t`, so it stops where the whole ray would have
//!    stopped; when `T ≤ 1 − t` it is not cast at all ([`RayLimits`]).
//!
//! A ray then stops only where the light reaching it through the front and its own part is
//! at most `1 − t`, so the image moves by at most `1 − t` per channel, the freedom
//! in-process early termination already takes, and at `t = 1` not at all (thresholds stay
//! 1, and a ray is left out only behind an exactly opaque block, which `OVER` weights by
//! zero up to its own rounding). Every bound is conservative (block maxima, upward rounding
//! to 1/65535, a pixel left uncast counting as fully transmissive), up to 2·10⁻¹¹ of
//! transmittance lost to the f64 product.
//!
//! Levels are 16-bit: near the threshold that matters (`1 − t = 0.01`) an 8-bit level
//! is off by up to 40 %, which left rays behind an almost opaque front cast for nothing.
//!
//! How the maps travel and when they are known is the caller's business (the cluster
//! predicts from the previous frame or from a low-resolution first pass,
//! [`FrontTransmittance::upsampled`], and re-casts the blocks the current frame's maps do
//! not confirm, [`FrontTransmittance::stale`]).

use crate::image::PartialImage;
use serde::{Deserialize, Serialize};

/// A transmittance level: `ceil(CLEAR · T)`.
pub type Level = u16;

/// The level of full transmittance (nothing in front, or nothing drawn).
pub const CLEAR: Level = u16::MAX;

const SCALE: f64 = CLEAR as f64;

/// Largest block side accepted.
pub const MAX_BLOCK: u32 = 64;

/// The block grid of a `width × height` image.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BlockGrid {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Side of a block in pixels (1..=[`MAX_BLOCK`]).
    pub block: u32,
}

impl BlockGrid {
    /// The grid of an image with `block`-pixel blocks (clamped to 1..=[`MAX_BLOCK`]).
    pub fn new(width: u32, height: u32, block: u32) -> Self {
        BlockGrid {
            width,
            height,
            block: block.clamp(1, MAX_BLOCK),
        }
    }

    /// Block columns.
    pub fn cols(&self) -> u32 {
        self.width.div_ceil(self.block)
    }

    /// Block rows.
    pub fn rows(&self) -> u32 {
        self.height.div_ceil(self.block)
    }

    /// Number of blocks.
    pub fn len(&self) -> usize {
        self.cols() as usize * self.rows() as usize
    }

    /// Whether the grid has no block.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The block holding pixel `(x, y)`.
    #[inline]
    pub fn block_of(&self, x: u32, y: u32) -> usize {
        (y / self.block) as usize * self.cols() as usize + (x / self.block) as usize
    }

    /// Words of a bit mask over the grid.
    pub fn words(&self) -> usize {
        self.len().div_ceil(64)
    }

    /// The pixels of block `b`: `(x0, y0, x1, y1)`, half-open, clipped to the image.
    #[inline]
    pub fn pixels_of(&self, b: usize) -> (u32, u32, u32, u32) {
        let cols = self.cols() as usize;
        let (x0, y0) = (
            (b % cols) as u32 * self.block,
            (b / cols) as u32 * self.block,
        );
        (
            x0,
            y0,
            (x0 + self.block).min(self.width),
            (y0 + self.block).min(self.height),
        )
    }
}

/// A rectangle of blocks `[x, y, w, h]`, in block units.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct BlockRect {
    /// First block column.
    pub x: u32,
    /// First block row.
    pub y: u32,
    /// Block columns.
    pub w: u32,
    /// Block rows.
    pub h: u32,
}

impl BlockRect {
    /// Number of blocks.
    pub fn area(&self) -> usize {
        self.w as usize * self.h as usize
    }
}

/// Why a transmittance map or mask from elsewhere is refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum OcclusionError {
    /// The rectangle reaches past the grid.
    #[error("block rectangle {rect:?} reaches past the {cols}x{rows} block grid")]
    RectOutside {
        /// The rectangle.
        rect: BlockRect,
        /// Grid columns.
        cols: u32,
        /// Grid rows.
        rows: u32,
    },
    /// The bytes are not an LZ4 block of levels ([`encode_levels`]).
    #[error("{what}: not an LZ4 block of levels ({why})")]
    Encoding {
        /// What was being read.
        what: &'static str,
        /// The decoder's complaint.
        why: String,
    },
    /// The number of values does not match.
    #[error("{what}: {got} values where {expected} were expected")]
    Length {
        /// What was being read.
        what: &'static str,
        /// Values received.
        got: usize,
        /// Values the grid or rectangle calls for.
        expected: usize,
    },
}

/// One worker's per-block transmittance over a rectangle of blocks ([`CLEAR`] = fully
/// transmissive, the value of every block outside the rectangle).
#[derive(Clone, Debug, PartialEq)]
pub struct Transmittance {
    /// The grid.
    pub grid: BlockGrid,
    /// The blocks stored.
    pub rect: BlockRect,
    /// Per stored block, row-major: `ceil(CLEAR · max(1 − α))` over its pixels.
    pub q: Vec<Level>,
}

/// `ceil(CLEAR · (1 − α))`, clamped to `0..=CLEAR`: never below the true transmittance, and
/// 0 only where the pixel is exactly opaque.
#[inline]
pub fn quantize(alpha: f32) -> Level {
    let t = 1.0 - alpha as f64;
    if t.is_nan() {
        return CLEAR;
    }
    if t <= 0.0 {
        return 0;
    }
    level_up(t * SCALE)
}

/// `ceil(x)` clamped to `1..=CLEAR` (NaN: 1; the callers never pass one). Without a target
/// feature for it (SSE4.1), `f64::ceil` is a call into libm, and the levels of every
/// block of a frame are rounded on the occlusion maps' critical path: a truncation and one
/// compare instead.
#[inline]
fn level_up(x: f64) -> Level {
    let t = x as u32; // truncates; saturates below 0 and NaN to 0, at and past 2^32 to MAX
    let up = t.saturating_add(((t as f64) < x) as u32);
    up.clamp(1, CLEAR as u32) as Level
}

/// Levels as they travel: little endian, the bytes shuffled (every low byte, then every
/// high byte) and LZ4-compressed. A map is mostly runs of [`CLEAR`] and of 0 (outside a
/// worker's footprint, behind opaque horizons), so a 1280×720 frame's 230 400 blocks,
/// 460 800 bytes raw, shrink to a few kilobytes: eight workers' maps each way took about
/// 15 ms over one coordinator's QUIC connections on 16 cores when they went raw.
///
/// The two byte planes are written straight from the levels (no little-endian copy to
/// shuffle): the coordinator encodes one map per position behind the last to report, on the
/// frame's critical path.
pub fn encode_levels(q: &[Level]) -> Vec<u8> {
    let n = q.len();
    let mut planes = vec![0u8; 2 * n];
    let (lo, hi) = planes.split_at_mut(n);
    for ((&v, l), h) in q.iter().zip(lo).zip(hi) {
        let [a, b] = v.to_le_bytes();
        *l = a;
        *h = b;
    }
    lz4_flex::block::compress(&planes)
}

/// The largest [`encode_levels`] of `count` levels.
pub fn max_encoded_len(count: usize) -> usize {
    lz4_flex::block::get_maximum_output_size(count * 2)
}

/// Exactly `count` levels from [`encode_levels`]'s bytes. The caller bounds `count` (it
/// sizes the buffer): data that would decompress to more is refused before it is written.
pub fn decode_levels(
    bytes: &[u8],
    count: usize,
    what: &'static str,
) -> Result<Vec<Level>, OcclusionError> {
    let raw =
        lz4_flex::block::decompress(bytes, count * 2).map_err(|e| OcclusionError::Encoding {
            what,
            why: e.to_string(),
        })?;
    if raw.len() != count * 2 {
        return Err(OcclusionError::Length {
            what,
            got: raw.len() / 2,
            expected: count,
        });
    }
    let (lo, hi) = raw.split_at(count);
    Ok(lo
        .iter()
        .zip(hi)
        .map(|(&l, &h)| Level::from_le_bytes([l, h]))
        .collect())
}

impl Transmittance {
    /// Reduces a partial image to `block`-pixel blocks: pixels outside its rectangle are
    /// transparent.
    pub fn of_image(img: &PartialImage, block: u32) -> Self {
        let grid = BlockGrid::new(img.width, img.height, block);
        let b = grid.block;
        let r = img.rect;
        if r.is_empty() {
            return Transmittance {
                grid,
                rect: BlockRect::default(),
                q: Vec::new(),
            };
        }
        let rect = BlockRect {
            x: r.x / b,
            y: r.y / b,
            w: (r.x + r.w).div_ceil(b) - r.x / b,
            h: (r.y + r.h).div_ceil(b) - r.y / b,
        };
        // The level of a block is the largest of its pixels', and `quantize` never rises
        // with alpha, so it is the level of the block's least alpha: one quantization per
        // block, not per pixel. Blocks the pixel rectangle covers only partly hold
        // transparent pixels outside it (alpha 0). A NaN alpha counts as 0, whose level,
        // CLEAR, is also NaN's.
        let mut least = vec![f32::INFINITY; rect.area()];
        for by in 0..rect.h {
            for bx in 0..rect.w {
                let (x0, y0) = ((rect.x + bx) * b, (rect.y + by) * b);
                let (x1, y1) = ((x0 + b).min(img.width), (y0 + b).min(img.height));
                let whole = x0 >= r.x && y0 >= r.y && x1 <= r.x + r.w && y1 <= r.y + r.h;
                if !whole {
                    least[(by * rect.w + bx) as usize] = 0.0;
                }
            }
        }
        // Each row's pixels in runs of one block each (no division per pixel: a worker
        // computes this for its whole image between its cast and its map, on the frame's
        // critical path).
        for row in 0..r.h {
            let y = r.y + row;
            let by = y / b - rect.y;
            let line = &img.pixels[(row * r.w) as usize..((row + 1) * r.w) as usize];
            let blocks = &mut least[(by * rect.w) as usize..((by + 1) * rect.w) as usize];
            // The first block may start left of the rectangle.
            let mut start = 0usize;
            for (i, least) in blocks.iter_mut().enumerate() {
                let end = (((rect.x + i as u32 + 1) * b).min(r.x + r.w) - r.x) as usize;
                let mut m = *least;
                for p in &line[start..end] {
                    let a = if p[3].is_nan() { 0.0 } else { p[3] };
                    if a < m {
                        m = a;
                    }
                }
                *least = m;
                start = end;
            }
        }
        let q = least.into_iter().map(quantize).collect();
        Transmittance { grid, rect, q }
    }

    /// Checks a map received from elsewhere against the grid it claims.
    pub fn checked(
        grid: BlockGrid,
        rect: BlockRect,
        q: Vec<Level>,
    ) -> Result<Self, OcclusionError> {
        Self::check_rect(grid, rect)?;
        if q.len() != rect.area() {
            return Err(OcclusionError::Length {
                what: "block transmittance",
                got: q.len(),
                expected: rect.area(),
            });
        }
        Ok(Transmittance { grid, rect, q })
    }

    fn check_rect(grid: BlockGrid, rect: BlockRect) -> Result<(), OcclusionError> {
        let inside = rect.x.checked_add(rect.w).is_some_and(|e| e <= grid.cols())
            && rect.y.checked_add(rect.h).is_some_and(|e| e <= grid.rows());
        if !inside {
            return Err(OcclusionError::RectOutside {
                rect,
                cols: grid.cols(),
                rows: grid.rows(),
            });
        }
        Ok(())
    }

    /// A map received from elsewhere as [`encode_levels`] bytes: the rectangle is checked
    /// against the grid before its area sizes anything.
    pub fn decoded(grid: BlockGrid, rect: BlockRect, bytes: &[u8]) -> Result<Self, OcclusionError> {
        Self::check_rect(grid, rect)?;
        let q = decode_levels(bytes, rect.area(), "block transmittance")?;
        Ok(Transmittance { grid, rect, q })
    }

    /// The value of block `(bx, by)`.
    #[inline]
    pub fn at(&self, bx: u32, by: u32) -> Level {
        let r = &self.rect;
        if bx < r.x || by < r.y || bx >= r.x + r.w || by >= r.y + r.h {
            return CLEAR;
        }
        self.q[((by - r.y) * r.w + (bx - r.x)) as usize]
    }
}

/// One bit per block of a grid.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BlockMask {
    /// The grid.
    pub grid: BlockGrid,
    /// Bit `i % 64` of word `i / 64` is block `i` (row-major).
    pub bits: Vec<u64>,
}

impl BlockMask {
    /// No block set.
    pub fn empty(grid: BlockGrid) -> Self {
        BlockMask {
            grid,
            bits: vec![0; grid.words()],
        }
    }

    /// Whether block `i` is set.
    #[inline]
    pub fn get(&self, i: usize) -> bool {
        self.bits[i / 64] >> (i % 64) & 1 == 1
    }

    /// Sets block `i`.
    #[inline]
    pub fn set(&mut self, i: usize) {
        self.bits[i / 64] |= 1 << (i % 64);
    }

    /// Whether the block holding pixel `(x, y)` is set.
    #[inline]
    pub fn pixel(&self, x: u32, y: u32) -> bool {
        self.get(self.grid.block_of(x, y))
    }

    /// Blocks set.
    pub fn count(&self) -> u64 {
        self.bits.iter().map(|w| w.count_ones() as u64).sum()
    }

    /// Whether any block is set.
    pub fn any(&self) -> bool {
        self.bits.iter().any(|&w| w != 0)
    }

    /// The smallest pixel rectangle holding every block set (clipped to the grid's
    /// pixels), or `None` when none is.
    pub fn pixel_bounds(&self) -> Option<crate::image::Rect> {
        let cols = self.grid.cols() as usize;
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for (wi, &w) in self.bits.iter().enumerate() {
            let mut w = w;
            while w != 0 {
                let b = wi * 64 + w.trailing_zeros() as usize;
                w &= w - 1;
                let (x, y) = (b % cols, b / cols);
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
            }
        }
        if x0 == usize::MAX {
            return None;
        }
        let (px0, py0, _, _) = self.grid.pixels_of(y0 * cols + x0);
        let (_, _, px1, py1) = self.grid.pixels_of(y1 * cols + x1);
        Some(crate::image::Rect::spanning(px0, py0, px1, py1))
    }
}

/// The transmittance of everything in front of one position of the visibility order, per
/// block of the whole grid: `ceil(CLEAR · T)` ([`CLEAR`]: nothing in front; 0: exactly
/// opaque).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrontTransmittance {
    /// The grid.
    pub grid: BlockGrid,
    /// Per block, row-major.
    pub q: Vec<Level>,
}

impl FrontTransmittance {
    /// Nothing in front.
    pub fn clear(grid: BlockGrid) -> Self {
        FrontTransmittance {
            grid,
            q: vec![CLEAR; grid.len()],
        }
    }

    /// Checks a map received from elsewhere: one value per block of the grid.
    pub fn checked(grid: BlockGrid, q: Vec<Level>) -> Result<Self, OcclusionError> {
        if q.len() != grid.len() {
            return Err(OcclusionError::Length {
                what: "front transmittance",
                got: q.len(),
                expected: grid.len(),
            });
        }
        Ok(FrontTransmittance { grid, q })
    }

    /// A map received from elsewhere as [`encode_levels`] bytes, one level per block.
    pub fn decoded(grid: BlockGrid, bytes: &[u8]) -> Result<Self, OcclusionError> {
        let q = decode_levels(bytes, grid.len(), "front transmittance")?;
        Ok(FrontTransmittance { grid, q })
    }

    /// The termination threshold of a ray in `block` for the whole-ray threshold
    /// `threshold`: `None` when the front lets at most `1 − threshold` through (the ray
    /// need not be cast), else the largest own opacity the ray needs, `1 − (1 − t)/T`,
    /// rounded up to an f32 (never below it, so what a ray stopped there leaves unseen
    /// stays within `1 − t`).
    #[inline]
    pub fn ray_threshold(&self, block: usize, threshold: f32) -> Option<f32> {
        let q = self.q[block];
        if q == CLEAR {
            return Some(threshold);
        }
        let t = threshold.clamp(0.0, 1.0) as f64;
        let front = q as f64 / SCALE;
        if front <= 1.0 - t {
            return None;
        }
        let own = 1.0 - (1.0 - t) / front;
        // Rounded up: a ray that stops at alpha e loses at most front·(1 − e) behind, which
        // must stay within 1 − t, so e may not fall below `own` (it stays ≤ t: own < t
        // where the front is not clear, and t is an f32).
        let mut e = own as f32;
        if (e as f64) < own {
            e = f32::from_bits(e.to_bits() + 1);
        }
        Some(e)
    }

    /// Blocks whose rays need not be cast at all for `threshold`.
    pub fn hidden(&self, threshold: f32) -> BlockMask {
        let mut m = BlockMask::empty(self.grid);
        for i in 0..self.q.len() {
            if self.ray_threshold(i, threshold).is_none() {
                m.set(i);
            }
        }
        m
    }

    /// The blocks of `images` (each cast by itself with this map's thresholds, a
    /// prediction: one per region a worker casts) that must be cast again with `actual`'s:
    /// where a pixel was left out that `actual` does not leave out, or where a ray stopped
    /// at this map's threshold (its alpha reached it) short of `actual`'s. A ray whose
    /// alpha stayed below its threshold ran to the end of its region and is complete
    /// whatever lies in front. The test needs each ray's own alpha: in a composite of
    /// several regions, one region's ray that stopped short can hide behind another's
    /// opacity.
    pub fn stale(
        &self,
        actual: &FrontTransmittance,
        images: &[&PartialImage],
        threshold: f32,
    ) -> BlockMask {
        assert_eq!(self.grid, actual.grid);
        for image in images {
            assert_eq!(
                (image.width, image.height),
                (self.grid.width, self.grid.height)
            );
        }
        let mut m = BlockMask::empty(self.grid);
        for b in 0..self.q.len() {
            if actual.q[b] <= self.q[b] {
                // The front lets no more through than predicted: every threshold holds.
                continue;
            }
            let Some(ea) = actual.ray_threshold(b, threshold) else {
                continue;
            };
            let (x0, y0, x1, y1) = self.grid.pixels_of(b);
            let redo = match self.ray_threshold(b, threshold) {
                None => true,
                Some(ep) => images.iter().any(|image| {
                    (y0..y1).any(|y| {
                        (x0..x1).any(|x| {
                            let a = image.get(x, y)[3];
                            a >= ep && a < ea
                        })
                    })
                }),
            };
            if redo {
                m.set(b);
            }
        }
        m
    }

    /// This map, made in one-pixel blocks by a cheap first pass of the same camera at a
    /// lower resolution (this map's grid), as a prediction on `grid`: each block takes the
    /// largest level of the low-resolution pixels it overlaps on the image plane. Only a
    /// prediction: the full-resolution frame's own map checks it ([`stale`](Self::stale)).
    ///
    /// Both images share the vertical field of view and the centre, with square pixels, so
    /// a low-resolution pixel spans `height / low height` pixels both ways; with sides that
    /// are not multiples of the scale that is not the scale itself (a 721-row frame at 1/4
    /// renders 181 rows of 3.98 pixels, and `y / 4` put the bottom rows 3 pixels off).
    pub fn upsampled(&self, grid: BlockGrid) -> FrontTransmittance {
        let (lw, lh) = (self.grid.width, self.grid.height);
        if self.q.is_empty() || lw == 0 || lh == 0 || grid.height == 0 {
            return FrontTransmittance::clear(grid);
        }
        // Full-resolution plane position → low-resolution pixel coordinate, per axis.
        let s = lh as f64 / grid.height as f64;
        let to_low =
            |p: u32, side: u32, low: u32| (p as f64 - side as f64 / 2.0) * s + low as f64 / 2.0;
        // The low pixels `[p0, p1)` overlaps (at least one, clamped to the image).
        let span = |p0: u32, p1: u32, side: u32, low: u32| {
            let a = to_low(p0, side, low).floor().max(0.0) as u32;
            let b = (to_low(p1, side, low).ceil() as u32).max(a + 1);
            (a.min(low - 1), (b - 1).min(low - 1))
        };
        let q = (0..grid.len())
            .map(|b| {
                let (x0, y0, x1, y1) = grid.pixels_of(b);
                let (lx0, lx1) = span(x0, x1, grid.width, lw);
                let (ly0, ly1) = span(y0, y1, grid.height, lh);
                (ly0..=ly1)
                    .flat_map(|y| (lx0..=lx1).map(move |x| (x, y)))
                    .map(|(x, y)| self.q[self.grid.block_of(x, y)])
                    .max()
                    .unwrap_or(CLEAR)
            })
            .collect();
        FrontTransmittance { grid, q }
    }

    /// This map with each block raised to the largest level within `radius` blocks (a
    /// square window, clipped at the edges): a prediction for a camera that has moved
    /// content by up to `radius` blocks on screen. Raising a level only lets more light
    /// through, so rays are cast further and fewer blocks turn out [`stale`](Self::stale);
    /// what is left out still obeys the same bound. Linear in the blocks whatever the
    /// radius (a sliding maximum along rows, then columns).
    pub fn dilated(&self, radius: u32) -> FrontTransmittance {
        let (cols, rows) = (self.grid.cols() as usize, self.grid.rows() as usize);
        if radius == 0 || self.q.is_empty() {
            return self.clone();
        }
        let r = radius as usize;
        let mut rows_done = vec![CLEAR; self.q.len()];
        for y in 0..rows {
            sliding_max(&self.q[y * cols..(y + 1) * cols], r, |i, v| {
                rows_done[y * cols + i] = v
            });
        }
        let mut q = vec![CLEAR; self.q.len()];
        let mut column = vec![CLEAR; rows];
        for x in 0..cols {
            for (y, c) in column.iter_mut().enumerate() {
                *c = rows_done[y * cols + x];
            }
            sliding_max(&column, r, |i, v| q[i * cols + x] = v);
        }
        FrontTransmittance { grid: self.grid, q }
    }

    /// This map moved by `(dx, dy)` blocks (content at block `(x, y)` goes to `(x + dx,
    /// y + dy)`): a prediction for a camera under which content moved that far on screen.
    /// Blocks no block moves into are clear (nothing predicted in front: their rays are
    /// cast in full).
    pub fn shifted(&self, dx: i64, dy: i64) -> FrontTransmittance {
        let (cols, rows) = (self.grid.cols() as i64, self.grid.rows() as i64);
        if (dx, dy) == (0, 0) || self.q.is_empty() {
            return self.clone();
        }
        let mut q = vec![CLEAR; self.q.len()];
        for y in 0..rows {
            let sy = y - dy;
            if !(0..rows).contains(&sy) {
                continue;
            }
            for x in 0..cols {
                let sx = x - dx;
                if (0..cols).contains(&sx) {
                    q[(y * cols + x) as usize] = self.q[(sy * cols + sx) as usize];
                }
            }
        }
        FrontTransmittance { grid: self.grid, q }
    }

    /// Whether some block has anything in front.
    pub fn any(&self) -> bool {
        self.q.iter().any(|&q| q < CLEAR)
    }
}

/// `put(i, max(line[i − r ..= i + r]))` for every `i` (the window clipped to the line), with
/// a queue of candidate maxima: each element enters and leaves it once.
fn sliding_max(line: &[Level], r: usize, mut put: impl FnMut(usize, Level)) {
    let n = line.len();
    let mut queue = std::collections::VecDeque::with_capacity(n.min(2 * r + 1));
    // Element j enters when the window of i = j − r first holds it.
    let mut next = 0;
    for i in 0..n {
        while next < n && next <= i + r {
            while queue.back().is_some_and(|&b: &usize| line[b] <= line[next]) {
                queue.pop_back();
            }
            queue.push_back(next);
            next += 1;
        }
        while queue.front().is_some_and(|&f| f + r < i) {
            queue.pop_front();
        }
        put(i, line[*queue.front().expect("the window holds i")]);
    }
}

/// For each position of the visibility order (`layers[0]` in front, all on one grid): the
/// transmittance of the layers in front of it. A zero factor stays exactly zero; every
/// other product is rounded up.
pub fn front_of(layers: &[&Transmittance]) -> Vec<FrontTransmittance> {
    let Some(first) = layers.first() else {
        return Vec::new();
    };
    let mut acc = FrontAccumulator::new(first.grid);
    let mut out = Vec::with_capacity(layers.len());
    out.push(FrontTransmittance::clear(first.grid));
    for layer in &layers[..layers.len() - 1] {
        out.push(acc.fold(layer));
    }
    out
}

/// [`front_of`] one layer at a time, front to back: after folding in the layers of
/// positions `0..k`, [`fold`](Self::fold) returns the map of position `k`. A cluster sends
/// each position its map as soon as the workers in front of it have reported, instead of
/// waiting for the slowest worker of the frame.
#[derive(Clone, Debug)]
pub struct FrontAccumulator {
    grid: BlockGrid,
    /// The exact product (in f64) of the rounded-up factors so far, per block.
    front: Vec<f64>,
    /// Its level.
    level: Vec<Level>,
    folded: usize,
}

impl FrontAccumulator {
    /// Nothing folded in: the map of position 0 (clear).
    pub fn new(grid: BlockGrid) -> Self {
        FrontAccumulator {
            grid,
            front: vec![1.0; grid.len()],
            level: vec![CLEAR; grid.len()],
            folded: 0,
        }
    }

    /// Layers folded in so far (the position whose map [`fold`](Self::fold) returned last,
    /// or 0).
    pub fn folded(&self) -> usize {
        self.folded
    }

    /// Folds in the next layer of the visibility order and returns the transmittance of
    /// everything folded so far (the map of the position behind it). A zero factor stays
    /// exactly zero; every other product is rounded up. A layer changes only the blocks of
    /// its rectangle where it is not CLEAR, so only those are worked out again.
    pub fn fold(&mut self, layer: &Transmittance) -> FrontTransmittance {
        assert_eq!(layer.grid, self.grid, "layers on different grids");
        let cols = self.grid.cols() as usize;
        let r = layer.rect;
        for (row, by) in (r.y..r.y + r.h).enumerate() {
            let start = by as usize * cols + r.x as usize;
            let own = &layer.q[row * r.w as usize..(row + 1) * r.w as usize];
            let front = &mut self.front[start..start + r.w as usize];
            let level = &mut self.level[start..start + r.w as usize];
            for ((&q, f), l) in own.iter().zip(front).zip(level) {
                if q == CLEAR {
                    continue; // a factor of exactly 1
                }
                // (A floor far below 1/255 keeps a positive product from underflowing to
                // an exact zero.)
                *f = if q == 0 || *f == 0.0 {
                    0.0
                } else {
                    (*f * (q as f64 / SCALE)).max(1e-300)
                };
                // Up; only an exact zero maps to 0. (The 1e-6 keeps a product that is a
                // whole number of levels but came out an ulp above it from rounding up a
                // whole level; it can understate a transmittance by at most 2e-11.)
                *l = if *f == 0.0 {
                    0
                } else {
                    level_up(*f * SCALE - 1e-6)
                };
            }
        }
        self.folded += 1;
        FrontTransmittance {
            grid: self.grid,
            q: self.level.clone(),
        }
    }
}

/// How a worker casts its rays under cross-worker occlusion: each ray's termination
/// threshold from the front transmittance of its block, and optionally only the blocks set
/// in `only` (a re-cast).
#[derive(Clone, Copy, Debug)]
pub struct RayLimits<'a> {
    /// What lies in front, per block.
    pub front: &'a FrontTransmittance,
    /// Cast only these blocks (`None`: all).
    pub only: Option<&'a BlockMask>,
    /// The whole ray's threshold (`render.early_termination`).
    pub threshold: f32,
}

impl RayLimits<'_> {
    /// The termination threshold of the ray through pixel `(x, y)`, or `None` when it is
    /// not cast.
    #[inline]
    pub fn ray(&self, x: u32, y: u32) -> Option<f32> {
        let b = self.front.grid.block_of(x, y);
        if self.only.is_some_and(|m| !m.get(b)) {
            return None;
        }
        self.front.ray_threshold(b, self.threshold)
    }

    /// Whether no ray of the pixel rectangle `[x, x + w) × [y, y + h)` is cast.
    pub fn none_in(&self, x: u32, y: u32, w: u32, h: u32) -> bool {
        if w == 0 || h == 0 {
            return true;
        }
        let cols = self.front.grid.cols() as usize;
        let b = self.front.grid.block;
        let (bx0, by0) = (x / b, y / b);
        let (bx1, by1) = ((x + w - 1) / b, (y + h - 1) / b);
        (by0..=by1).all(|by| {
            (bx0..=bx1).all(|bx| {
                let i = by as usize * cols + bx as usize;
                self.only.is_some_and(|m| !m.get(i))
                    || self.front.ray_threshold(i, self.threshold).is_none()
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::{composite_front_to_back, Rect, Rgba};
    use proptest::prelude::*;

    /// A mask's pixel bounds hold exactly its blocks' pixels: the least and greatest block
    /// column and row, clipped at the image's edge (blocks of 4 on a 10 × 7 image).
    #[test]
    fn pixel_bounds_hold_the_blocks_set() {
        let grid = BlockGrid::new(10, 7, 4); // 3 × 2 blocks, the last column and row short
        let mut m = BlockMask::empty(grid);
        assert_eq!(m.pixel_bounds(), None);
        m.set(1);
        assert_eq!(
            m.pixel_bounds(),
            Some(Rect {
                x: 4,
                y: 0,
                w: 4,
                h: 4
            })
        );
        m.set(5); // column 2, row 1: pixels 8..10 × 4..7
        assert_eq!(
            m.pixel_bounds(),
            Some(Rect {
                x: 4,
                y: 0,
                w: 6,
                h: 7
            })
        );
        let mut one = BlockMask::empty(grid);
        one.set(3);
        assert_eq!(
            one.pixel_bounds(),
            Some(Rect {
                x: 0,
                y: 4,
                w: 4,
                h: 3
            })
        );
    }

    /// A shifted map moves every level by whole blocks; blocks nothing moves into are clear.
    #[test]
    fn a_shifted_map_moves_its_levels_and_clears_what_it_uncovers() {
        let grid = BlockGrid::new(8, 6, 2); // 4 × 3 blocks
        let q: Vec<Level> = (0..12).map(|i| i as Level * 1000).collect();
        let map = FrontTransmittance::checked(grid, q.clone()).unwrap();
        assert_eq!(map.shifted(0, 0), map);
        let s = map.shifted(1, -1);
        for y in 0..3i64 {
            for x in 0..4i64 {
                let (sx, sy) = (x - 1, y + 1);
                let want = if (0..4).contains(&sx) && (0..3).contains(&sy) {
                    q[(sy * 4 + sx) as usize]
                } else {
                    CLEAR
                };
                assert_eq!(s.q[(y * 4 + x) as usize], want, "block ({x}, {y})");
            }
        }
        // Past the edge: nothing is left in front.
        assert!(!map.shifted(4, 0).any() && !map.shifted(0, -3).any());
        assert!(map.shifted(-3, 2).any());
    }

    /// Every per-ray threshold keeps what a ray stopped there leaves unseen within 1 − t,
    /// `front · (1 − e) ≤ 1 − t` on the f32 `e`, to f64 rounding (a threshold rounded down
    /// to an f32 breaks it by up to an f32 ulp).
    #[test]
    fn ray_thresholds_never_lose_more_than_one_minus_t() {
        let levels: Vec<Level> = (1..CLEAR).step_by(7).collect();
        let grid = BlockGrid::new(levels.len() as u32, 1, 1);
        let map = FrontTransmittance::checked(grid, levels.clone()).unwrap();
        let mut limited = 0;
        for t in [0.5f32, 0.9, 0.99, 0.999, 0.3333] {
            for (b, &q) in levels.iter().enumerate() {
                let front = q as f64 / SCALE;
                match map.ray_threshold(b, t) {
                    None => assert!(front <= 1.0 - t as f64, "q {q}, t {t}"),
                    Some(e) => {
                        assert!(e <= t, "q {q}, t {t}: {e}");
                        // (1e-12: the f64 rounding of this check, far below an f32 ulp.)
                        let lost = front * (1.0 - e as f64);
                        assert!(
                            lost <= 1.0 - t as f64 + 1e-12,
                            "q {q}, t {t}: e {e} loses {lost}"
                        );
                        limited += 1;
                    }
                }
            }
        }
        assert!(limited > 10_000);
    }

    fn image(w: u32, h: u32, rect: Rect, alpha: impl Fn(u32, u32) -> f32) -> PartialImage {
        let mut pixels = Vec::new();
        for y in rect.y..rect.y + rect.h {
            for x in rect.x..rect.x + rect.w {
                let a = alpha(x, y);
                pixels.push([a * 0.5, a * 0.25, a, a]);
            }
        }
        PartialImage {
            width: w,
            height: h,
            rect,
            pixels,
        }
    }

    #[test]
    fn level_up_is_ceil_clamped() {
        let ceil = |x: f64| x.ceil().clamp(1.0, SCALE) as Level;
        let mut xs = vec![
            -1.0,
            -1e-6,
            0.0,
            1e-300,
            0.5,
            1.0,
            1.0 + 1e-12,
            2.0,
            65534.5,
            65535.0,
        ];
        xs.extend([
            65535.000001,
            1e6,
            4e9,
            4.3e9,
            1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ]);
        xs.push(f64::NAN);
        // Every level and its neighbours, as the products of `fold` land on them.
        for l in 0..=CLEAR as u32 {
            let x = l as f64;
            xs.extend([x, f64::from_bits(x.to_bits() + 1), x - 1e-6, x + 0.5]);
        }
        for x in xs {
            let want = if x.is_nan() { 1 } else { ceil(x) };
            assert_eq!(level_up(x), want, "{x:e}");
        }
    }

    #[test]
    fn quantize_rounds_up_and_is_zero_only_when_opaque() {
        assert_eq!(quantize(1.0), 0);
        assert_eq!(quantize(0.0), CLEAR);
        assert_eq!(quantize(1.0 - 1e-7), 1);
        assert_eq!(quantize(0.5), 32768);
        assert_eq!(quantize(f32::NAN), CLEAR);
        assert_eq!(quantize(-1e30), CLEAR);
        assert_eq!(quantize(f32::NEG_INFINITY), CLEAR);
        for a in [0.0f32, 0.1, 0.33, 0.5, 0.9, 0.99, 0.999_99] {
            assert!(quantize(a) as f64 / SCALE >= 1.0 - a as f64, "{a}");
        }
        let q = vec![0, 1, 258, CLEAR];
        assert_eq!(
            decode_levels(&encode_levels(&q), q.len(), "test").unwrap(),
            q
        );
        // Too few, too many, not LZ4.
        let e = encode_levels(&q);
        assert!(matches!(
            decode_levels(&e, q.len() + 1, "test"),
            Err(OcclusionError::Length { .. })
        ));
        assert!(decode_levels(&e, q.len() - 1, "test").is_err());
        assert!(decode_levels(&[0xF0, 1, 2, 3], q.len(), "test").is_err());
        // A large map of runs compresses well, and within its bound.
        let runs: Vec<Level> = (0..230_400u32)
            .map(|i| if (i / 640) % 3 == 0 { 0 } else { CLEAR })
            .collect();
        let e = encode_levels(&runs);
        assert!(e.len() < runs.len() / 50, "{} bytes", e.len());
        assert!(e.len() <= max_encoded_len(runs.len()));
        assert_eq!(decode_levels(&e, runs.len(), "test").unwrap(), runs);
        // The bytes are those of the definition: little endian, shuffled by
        // `store::shuffle`, LZ4.
        let mixed: Vec<Level> = (0..1001u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 16) as Level)
            .collect();
        let raw: Vec<u8> = mixed.iter().flat_map(|v| v.to_le_bytes()).collect();
        let want = lz4_flex::block::compress(&crate::store::shuffle(&raw, 2));
        assert_eq!(encode_levels(&mixed), want);
        assert_eq!(decode_levels(&want, mixed.len(), "test").unwrap(), mixed);
    }

    #[test]
    fn blocks_partly_outside_the_image_rectangle_count_as_transmissive() {
        // An opaque rectangle from (1, 1) to (8, 8) in a 10×10 image: only the block
        // (1, 1) (pixels 4..8) is covered whole.
        let img = image(
            10,
            10,
            Rect {
                x: 1,
                y: 1,
                w: 7,
                h: 7,
            },
            |_, _| 1.0,
        );
        let t = Transmittance::of_image(&img, 4);
        assert_eq!(
            t.rect,
            BlockRect {
                x: 0,
                y: 0,
                w: 2,
                h: 2
            }
        );
        assert_eq!(t.at(1, 1), 0);
        assert_eq!(t.at(0, 0), CLEAR);
        assert_eq!(t.at(1, 0), CLEAR);
        assert_eq!(t.at(2, 2), CLEAR);
        // The image edge: a 10-pixel-wide image's last block is 2 pixels wide and is
        // covered whole by a rectangle reaching the edge.
        let img = image(
            10,
            10,
            Rect {
                x: 8,
                y: 8,
                w: 2,
                h: 2,
            },
            |_, _| 1.0,
        );
        assert_eq!(Transmittance::of_image(&img, 4).at(2, 2), 0);
    }

    #[test]
    fn thresholds_follow_the_front_and_stay_exact_at_one() {
        let g = 8;
        let full = Rect {
            x: 0,
            y: 0,
            w: g,
            h: g,
        };
        // Front: opaque left half, 0.999 right half.
        let front = image(g, g, full, |x, _| if x < 4 { 1.0 } else { 0.999 });
        let back = image(g, g, full, |_, _| 0.5);
        let (tf, tb) = (
            Transmittance::of_image(&front, 4),
            Transmittance::of_image(&back, 4),
        );
        let f = front_of(&[&tf, &tb, &tb]);
        assert!(!f[0].any(), "nothing lies in front of the first position");
        // 1 − 0.999f32 = 0.00099998713 → 66 levels; times 32768/65535 = 33.0005 → 34.
        assert_eq!(f[1].q, vec![0, 66, 0, 66]);
        assert_eq!(f[2].q, vec![0, 34, 0, 34]);
        // At t = 1 only the exactly opaque blocks are left out; the others keep t = 1.
        assert_eq!(f[1].hidden(1.0).count(), 2);
        assert_eq!(f[1].ray_threshold(1, 1.0), Some(1.0));
        assert_eq!(f[1].ray_threshold(0, 1.0), None);
        // At 0.99 the 0.999 half is hidden too.
        assert_eq!(f[1].hidden(0.99).count(), 4);
        // Two half-opaque layers pass 1/4, quantized up to (32768/65535)^2 → 16385 levels:
        // the third position's rays need only 1 − 0.01 · 65535/16385 = 0.96000 of their own.
        let f = front_of(&[&tb, &tb, &tb]);
        assert_eq!(f[1].q[0], 32768);
        assert_eq!(f[2].q[0], 16385);
        let e = f[2].ray_threshold(0, 0.99).unwrap();
        assert!(
            (e - (1.0 - 0.01 * SCALE / 16385.0) as f32).abs() < 1e-6,
            "{e}"
        );
        assert!(((1.0 - e as f64) * 16385.0 / SCALE) <= 0.01 + 1e-12);
        // A prediction that promised less light than there is goes stale where a ray was
        // left out or stopped short of the actual threshold; a ray that ran out of its
        // region below its threshold is complete.
        let img = |a: f32| image(g, g, full, move |x, y| if x < 4 && y < 4 { a } else { 0.3 });
        let actual = &f[0]; // nothing in front after all
        let hidden = FrontTransmittance {
            grid: f[2].grid,
            q: vec![600; 4],
        };
        assert_eq!(
            hidden.stale(actual, &[&img(0.0)], 0.99).count(),
            4,
            "left out"
        );
        assert_eq!(
            f[1].stale(actual, &[&img(0.97)], 0.99).count(),
            0,
            "below 0.980: ran out"
        );
        let pred = FrontTransmittance {
            grid: f[2].grid,
            q: vec![16385, CLEAR, CLEAR, CLEAR],
        };
        let e = pred.ray_threshold(0, 0.99).unwrap();
        assert_eq!(
            pred.stale(actual, &[&img(e)], 0.99).count(),
            1,
            "stopped at its threshold"
        );
        assert_eq!(
            pred.stale(actual, &[&img(0.995)], 0.99).count(),
            0,
            "past both"
        );
        assert_eq!(
            pred.stale(actual, &[&img(e * 0.99)], 0.99).count(),
            0,
            "ran out"
        );
        assert!(
            !f[0].stale(&f[1], &[&img(0.0)], 0.99).any(),
            "less light than predicted"
        );
        // Two regions of one worker, each cast with the predicted limits: the front one
        // stopped at its threshold, the back one is nearly opaque. Their composite passes
        // the actual threshold, but the front ray stopped short of it: stale.
        let front_leaf = img(e);
        let back_leaf = img(0.98);
        let both = PartialImage::from_full(
            g,
            g,
            &composite_front_to_back(g, g, &[&front_leaf, &back_leaf]),
        );
        assert!(both.get(0, 0)[3] >= 0.99);
        assert_eq!(
            pred.stale(actual, &[&both], 0.99).count(),
            0,
            "the composite hides it"
        );
        assert_eq!(
            pred.stale(actual, &[&front_leaf, &back_leaf], 0.99).count(),
            1,
            "each region's own alpha shows it"
        );
    }

    #[test]
    fn a_first_pass_map_upsamples_to_the_largest_level_it_overlaps() {
        // Sides that are multiples of the scale: a 1/4 pass of an 8 × 8 frame is 2 × 2,
        // and a low pixel covers exactly 4 × 4 pixels.
        let low = FrontTransmittance {
            grid: BlockGrid::new(2, 2, 1),
            q: vec![0, 100, 7, 9],
        };
        let up = low.upsampled(BlockGrid::new(8, 8, 2));
        assert_eq!(up.grid, BlockGrid::new(8, 8, 2));
        assert_eq!(
            up.q[..4],
            [0, 0, 100, 100],
            "pixels 0..4 are low pixel 0, 4..8 pixel 1"
        );
        assert_eq!(up.q[4..8], [0, 0, 100, 100]);
        assert_eq!(up.q[8..], [7, 7, 9, 9, 7, 7, 9, 9]);
        // A 10 × 7 frame: the 1/4 pass is 3 × 2 low pixels of 3.5 pixels (the vertical
        // field of view is shared), centred, so the low image reaches past the frame's
        // sides: pixel x lies at low x' = (x − 5) · 2/7 + 1.5.
        let low = FrontTransmittance {
            grid: BlockGrid::new(3, 2, 1),
            q: vec![0, 100, CLEAR, 7, 8, 9],
        };
        let up = low.upsampled(BlockGrid::new(10, 7, 2));
        // Block row 0 (pixels 0..2) lies in low row 0. Columns: pixels 0..2 → low
        // 0.07..0.64; 2..4 → 0.64..1.21 (low 0 and 1: the larger level, the clearer, wins);
        // 4..6 → low 1; 6..8 → 1.79..2.36 (low 1 and 2); 8..10 → low 2.
        assert_eq!(up.q[..5], [0, 100, 100, CLEAR, CLEAR]);
        // Block row 1, pixels 2..4 → low 0.57..1.14: rows 0 and 1.
        assert_eq!(up.q[5], 7);
        assert_eq!(up.q[9], CLEAR);
        // Block rows 2 and 3 (pixels 4..6, 6..7): low row 1.
        assert_eq!(up.q[10..15], [7, 8, 8, 9, 9]);
        assert_eq!(up.q[15], 7);
        // A 721-row frame at 1/4 renders 181 rows of 3.98 pixels: the last low row covers
        // pixels 717.01..721, so rows 718–720 lie in it (`y / 4` had only row 720) and row
        // 717, which straddles it, takes the clearer level of the two.
        let mut q = vec![CLEAR; 181];
        q[180] = 0;
        let low = FrontTransmittance {
            grid: BlockGrid::new(1, 181, 1),
            q,
        };
        let up = low.upsampled(BlockGrid::new(4, 721, 1));
        let row = |y: usize| up.q[y * 4];
        assert_eq!([row(716), row(717)], [CLEAR; 2]);
        assert_eq!([row(718), row(719), row(720)], [0; 3]);
        assert!(up.q.chunks(4).all(|r| r.iter().all(|&v| v == r[0])));
    }

    #[test]
    fn received_maps_and_masks_are_checked() {
        let grid = BlockGrid::new(10, 7, 4); // 3 × 2 blocks
        let r = BlockRect {
            x: 1,
            y: 0,
            w: 2,
            h: 2,
        };
        assert!(Transmittance::checked(grid, r, vec![0; 4]).is_ok());
        assert!(matches!(
            Transmittance::checked(grid, r, vec![0; 3]),
            Err(OcclusionError::Length { .. })
        ));
        let past = BlockRect { x: 2, ..r };
        assert!(matches!(
            Transmittance::checked(grid, past, vec![0; 4]),
            Err(OcclusionError::RectOutside { .. })
        ));
        let huge = BlockRect { x: u32::MAX, ..r };
        assert!(Transmittance::checked(grid, huge, vec![0; 4]).is_err());
    }

    /// The `g × g` images of `layers`, grey with each pixel's alpha, pixel `nan_at` of
    /// each (if any) NaN.
    fn layer_images(
        g: u32,
        layers: &[(Rect, Vec<f32>)],
        nan_at: Option<usize>,
    ) -> Vec<PartialImage> {
        layers
            .iter()
            .map(|(rect, alphas)| PartialImage {
                width: g,
                height: g,
                rect: *rect,
                pixels: alphas
                    .iter()
                    .enumerate()
                    .map(|(i, &a)| {
                        let a = if nan_at == Some(i) { f32::NAN } else { a };
                        [a, a, a, a] as Rgba
                    })
                    .collect(),
            })
            .collect()
    }

    fn layer_strategy(g: u32) -> impl Strategy<Value = Vec<(Rect, Vec<f32>)>> {
        let one = (0..g, 0..g, 1..=g, 1..=g).prop_flat_map(move |(x, y, w, h)| {
            let (w, h) = (w.min(g - x), h.min(g - y));
            let n = (w * h) as usize;
            let alpha = prop_oneof![Just(0.0f32), Just(1.0f32), 0.0f32..=1.0];
            (
                Just(Rect { x, y, w, h }),
                proptest::collection::vec(alpha, n),
            )
        });
        proptest::collection::vec(one, 1..6)
    }

    proptest! {
        /// Whatever the layers: a ray left uncast lies behind at most `1 − t` of light in
        /// every pixel of its block, and a ray stopped at its threshold `e` leaves at most
        /// `1 − t` passing through the front and its own part, so no pixel moves by more
        /// than early termination allows.
        #[test]
        fn every_limited_ray_stops_within_the_termination_bound(
            layers in layer_strategy(13),
            t in prop_oneof![Just(1.0f32), 0.5f32..1.0],
            block in 1u32..6,
        ) {
            let g = 13;
            let imgs = layer_images(g, &layers, None);
            let maps: Vec<Transmittance> =
                imgs.iter().map(|i| Transmittance::of_image(i, block)).collect();
            let refs: Vec<&Transmittance> = maps.iter().collect();
            let fronts = front_of(&refs);
            for pos in 1..imgs.len() {
                let front: Vec<&PartialImage> = imgs[..pos].iter().collect();
                let acc = composite_front_to_back(g, g, &front);
                let limits = RayLimits { front: &fronts[pos], only: None, threshold: t };
                for y in 0..g {
                    for x in 0..g {
                        let through = 1.0 - acc[(y * g + x) as usize][3] as f64;
                        let own = match limits.ray(x, y) {
                            None => 0.0,
                            Some(e) => {
                                prop_assert!(e <= t);
                                e as f64
                            }
                        };
                        prop_assert!(
                            through * (1.0 - own) <= (1.0 - t as f64) + 1e-6,
                            "pos {pos} ({x}, {y}): {through} passes the front, own {own}, t = {t}"
                        );
                        if t == 1.0 {
                            prop_assert!(limits.ray(x, y).is_none_or(|e| e == 1.0));
                        }
                    }
                }
            }
        }
    }

    proptest! {
        /// The sliding maximum equals the window maximum computed directly, on grids that
        /// are wider, taller or smaller than the window.
        #[test]
        fn dilated_takes_the_largest_level_within_the_radius(
            cols in 1u32..12,
            rows in 1u32..12,
            radius in 0u32..7,
            seed in any::<u64>(),
        ) {
            let grid = BlockGrid::new(cols * 2, rows * 2, 2);
            let mut x = seed | 1;
            let q: Vec<Level> = (0..grid.len())
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    // Few distinct levels, so ties are common.
                    [0, 7, 7, 300, CLEAR][(x % 5) as usize]
                })
                .collect();
            let map = FrontTransmittance::checked(grid, q).unwrap();
            let d = map.dilated(radius);
            let r = radius as i64;
            for by in 0..rows as i64 {
                for bx in 0..cols as i64 {
                    let mut want = 0;
                    for y in (by - r).max(0)..=(by + r).min(rows as i64 - 1) {
                        for x in (bx - r).max(0)..=(bx + r).min(cols as i64 - 1) {
                            want = want.max(map.q[(y * cols as i64 + x) as usize]);
                        }
                    }
                    prop_assert_eq!(d.q[(by * cols as i64 + bx) as usize], want, "block ({}, {})", bx, by);
                }
            }
        }
    }

    proptest! {
        /// The block maps equal their definitions worked out pixel by pixel and block by
        /// block: a block's level is the largest `quantize` of its pixels' alphas (CLEAR for
        /// a pixel outside the image's rectangle), and the front of a position is the f64
        /// product of the levels in front, rounded up.
        #[test]
        fn block_maps_equal_their_definitions(
            layers in layer_strategy(13),
            block in 1u32..6,
            nan in any::<bool>(),
        ) {
            let g = 13;
            let imgs = layer_images(g, &layers, nan.then_some(1));
            let maps: Vec<Transmittance> =
                imgs.iter().map(|i| Transmittance::of_image(i, block)).collect();
            let grid = BlockGrid::new(g, g, block);
            let level_of = |img: &PartialImage, b: usize| {
                let (x0, y0, x1, y1) = grid.pixels_of(b);
                (y0..y1)
                    .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        let r = img.rect;
                        if x < r.x || y < r.y || x >= r.x + r.w || y >= r.y + r.h {
                            CLEAR
                        } else {
                            quantize(img.pixels[((y - r.y) * r.w + x - r.x) as usize][3])
                        }
                    })
                    .max()
                    .unwrap()
            };
            for (img, map) in imgs.iter().zip(&maps) {
                for b in 0..grid.len() {
                    let (bx, by) = (b as u32 % grid.cols(), b as u32 / grid.cols());
                    prop_assert_eq!(map.at(bx, by), level_of(img, b), "block {}", b);
                }
            }
            let refs: Vec<&Transmittance> = maps.iter().collect();
            let fronts = front_of(&refs);
            prop_assert_eq!(fronts.len(), maps.len());
            for (pos, front) in fronts.iter().enumerate() {
                for b in 0..grid.len() {
                    let (bx, by) = (b as u32 % grid.cols(), b as u32 / grid.cols());
                    let mut t = 1.0f64;
                    for m in &maps[..pos] {
                        let q = m.at(bx, by);
                        t = if q == 0 || t == 0.0 { 0.0 } else { (t * (q as f64 / SCALE)).max(1e-300) };
                    }
                    let want = if t == 0.0 { 0 } else { (t * SCALE - 1e-6).ceil().clamp(1.0, SCALE) as Level };
                    prop_assert_eq!(front.q[b], want, "position {} block {}", pos, b);
                }
            }
        }
    }
}
