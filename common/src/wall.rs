//! Powerwall geometry: a grid of display tiles separated by mullions (bezels), seen by one
//! camera as one frustum, and rendered as one *stacked* image without the mullion pixels.
//!
//! * **The plane.** The camera's frustum covers the whole wall, mullions included:
//!   `cols·tile_w + (cols − 1)·mullion_x` by `rows·tile_h + (rows − 1)·mullion_y` pixels,
//!   so an object crossing a bezel lines up on both sides as it would through a window
//!   frame. Tile `(c, r)` (column 0 at the left, row 0 at the top) starts at plane pixel
//!   `(c·(tile_w + mullion_x), r·(tile_h + mullion_y))`.
//! * **The stacked image.** What is rendered and composited is `tile_w` wide and
//!   `tiles·tile_h` high: tile `t = r·cols + c` occupies rows `[t·tile_h, (t + 1)·tile_h)`.
//!   Pixels behind mullions are not in it, so they are neither cast nor composited. A tile
//!   is a contiguous run of rows, hence one contiguous span of the row-major pixel index,
//!   which is what lets compositing deliver each tile whole to the rank that drives it
//!   ([`crate::composite::build_plan_to`]).
//! * **Drivers.** Each tile has a driving rank. A rank's tiles must be consecutive in
//!   row-major order, so that its share of the stacked image is one span.

use serde::{Deserialize, Serialize};

/// The tile layout of a wall (pure geometry; `[wall]` in the scene adds drivers and
/// output options).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct WallGeometry {
    /// Tile columns.
    pub cols: u32,
    /// Tile rows.
    pub rows: u32,
    /// Tile width in pixels.
    pub tile_w: u32,
    /// Tile height in pixels.
    pub tile_h: u32,
    /// Bezel width between horizontally neighbouring tiles, in pixels.
    pub mullion_x: u32,
    /// Bezel height between vertically neighbouring tiles, in pixels.
    pub mullion_y: u32,
}

/// Why a wall layout is unusable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WallError {
    /// `wall.ranks` does not name one rank per tile.
    #[error("wall.ranks names {got} ranks for {tiles} tiles (one per tile, row-major from the top left)")]
    RankCount {
        /// Entries given.
        got: usize,
        /// Tiles.
        tiles: u32,
    },
    /// A driver that is not a worker.
    #[error("wall.ranks: tile {tile} is driven by rank {rank}, but there are {workers} workers (ranks 0..{workers})")]
    RankRange {
        /// The tile.
        tile: u32,
        /// Its rank.
        rank: u32,
        /// Workers.
        workers: usize,
    },
    /// A rank whose tiles are not consecutive.
    #[error("wall.ranks: rank {rank} drives tiles {first} and {later} but not tile {between}; a rank's tiles must be consecutive in row-major order (left to right, then top to bottom)")]
    NotConsecutive {
        /// The rank.
        rank: u32,
        /// One of its tiles.
        first: u32,
        /// A tile in between driven by another rank.
        between: u32,
        /// A later tile of the rank.
        later: u32,
    },
}

/// Largest side of a tile, in pixels.
pub const MAX_TILE_SIDE: u32 = 32768;
/// Largest number of tiles.
pub const MAX_TILES: u32 = 4096;
/// Largest number of pixels of the wall's plane (and so of its stacked image), below
/// `u32::MAX` so pixel indices and spans stay `u32`.
pub const MAX_WALL_PIXELS: u64 = 1 << 31;

impl WallGeometry {
    /// Checks the layout: counts and sizes positive and bounded, mullions bounded, the
    /// plane under [`MAX_WALL_PIXELS`].
    pub fn check(&self) -> Result<(), String> {
        let range = |key: &str, v: [u32; 2], lo: u32, hi: u32| {
            if v.iter().all(|&x| (lo..=hi).contains(&x)) {
                Ok(())
            } else {
                Err(format!(
                    "wall.{key} = [{}, {}]: each value must lie in {lo}..={hi}",
                    v[0], v[1]
                ))
            }
        };
        range("tiles", [self.cols, self.rows], 1, MAX_TILES)?;
        if self.cols as u64 * self.rows as u64 > MAX_TILES as u64 {
            return Err(format!(
                "wall.tiles = [{}, {}]: at most {MAX_TILES} tiles are supported",
                self.cols, self.rows
            ));
        }
        range("tile_size", [self.tile_w, self.tile_h], 1, MAX_TILE_SIDE)?;
        range(
            "mullion",
            [self.mullion_x, self.mullion_y],
            0,
            MAX_TILE_SIDE,
        )?;
        let (w, h) = self.plane_size_u64();
        if w * h > MAX_WALL_PIXELS || w > u32::MAX as u64 || h > u32::MAX as u64 {
            return Err(format!(
                "a wall of {}×{} tiles of {}×{} with mullions {}×{} is {w}×{h} pixels; at most {MAX_WALL_PIXELS} pixels are supported",
                self.cols, self.rows, self.tile_w, self.tile_h, self.mullion_x, self.mullion_y
            ));
        }
        Ok(())
    }

    fn plane_size_u64(&self) -> (u64, u64) {
        let w = self.cols as u64 * self.tile_w as u64
            + (self.cols as u64).saturating_sub(1) * self.mullion_x as u64;
        let h = self.rows as u64 * self.tile_h as u64
            + (self.rows as u64).saturating_sub(1) * self.mullion_y as u64;
        (w, h)
    }

    /// Number of tiles.
    pub fn tiles(&self) -> u32 {
        self.cols * self.rows
    }

    /// The frustum's image plane in pixels, mullions included (a checked layout).
    pub fn plane_size(&self) -> (u32, u32) {
        let (w, h) = self.plane_size_u64();
        (w as u32, h as u32)
    }

    /// The stacked image: `tile_w × tiles·tile_h`.
    pub fn stacked_size(&self) -> (u32, u32) {
        (self.tile_w, self.tiles() * self.tile_h)
    }

    /// Pixels of one tile.
    pub fn tile_pixels(&self) -> u32 {
        self.tile_w * self.tile_h
    }

    /// Column and row of tile `t` (row-major).
    pub fn tile_cr(&self, t: u32) -> (u32, u32) {
        (t % self.cols, t / self.cols)
    }

    /// Plane pixel of the top-left corner of tile `t`.
    pub fn tile_origin(&self, t: u32) -> (u32, u32) {
        let (c, r) = self.tile_cr(t);
        (
            c * (self.tile_w + self.mullion_x),
            r * (self.tile_h + self.mullion_y),
        )
    }

    /// The map from stacked-image pixels to plane pixels that ray generation uses.
    pub fn tile_map(&self) -> TileMap {
        TileMap {
            cols: self.cols,
            tile_h: self.tile_h,
            pitch_x: self.tile_w + self.mullion_x,
            pitch_y: self.tile_h + self.mullion_y,
        }
    }

    /// The row-major pixel span `[start, end)` of tile `t` in the stacked image.
    pub fn tile_span(&self, t: u32) -> (u32, u32) {
        let n = self.tile_pixels();
        (t * n, (t + 1) * n)
    }

    /// The default drivers of the tiles over `workers` ranks: consecutive runs of tiles,
    /// as even as possible; with fewer tiles than workers, tiles go to ranks spread over
    /// the range (`t·workers / tiles`).
    pub fn default_drivers(&self, workers: usize) -> Vec<u32> {
        let t = self.tiles() as u64;
        let w = workers.max(1) as u64;
        (0..t).map(|i| (i * w / t) as u32).collect()
    }

    /// Checks drivers: one per tile, each a worker rank, each rank's tiles consecutive.
    pub fn check_drivers(&self, drivers: &[u32], workers: usize) -> Result<(), WallError> {
        if drivers.len() != self.tiles() as usize {
            return Err(WallError::RankCount {
                got: drivers.len(),
                tiles: self.tiles(),
            });
        }
        for (t, &r) in drivers.iter().enumerate() {
            if r as usize >= workers {
                return Err(WallError::RankRange {
                    tile: t as u32,
                    rank: r,
                    workers,
                });
            }
        }
        let mut last: std::collections::HashMap<u32, usize> = Default::default();
        for (t, &r) in drivers.iter().enumerate() {
            if let Some(&prev) = last.get(&r) {
                if prev + 1 != t {
                    return Err(WallError::NotConsecutive {
                        rank: r,
                        first: prev as u32,
                        between: prev as u32 + 1,
                        later: t as u32,
                    });
                }
            }
            last.insert(r, t);
        }
        Ok(())
    }

    /// Per rank (`0..workers`), the span of the stacked image it drives (empty `(0, 0)` for
    /// ranks that drive no tile). The drivers must have passed
    /// [`check_drivers`](Self::check_drivers).
    pub fn driver_spans(&self, drivers: &[u32], workers: usize) -> Vec<(u32, u32)> {
        let mut spans = vec![(0u32, 0u32); workers];
        for (t, &r) in drivers.iter().enumerate() {
            let (s, e) = self.tile_span(t as u32);
            let cur = &mut spans[r as usize];
            *cur = if cur.0 == cur.1 { (s, e) } else { (cur.0, e) };
        }
        spans
    }
}

/// The file of tile `(c, r)` for the output `base`: `out/f.png` → `out/f_c{c}r{r}.png`
/// (the suffix goes before the extension; a name without one gets it at the end).
pub fn tile_path(base: &std::path::Path, c: u32, r: u32) -> std::path::PathBuf {
    let stem = base
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match base.extension() {
        Some(e) => format!("{stem}_c{c}r{r}.{}", e.to_string_lossy()),
        None => format!("{stem}_c{c}r{r}"),
    };
    base.with_file_name(name)
}

/// One tile's output files.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileFiles {
    /// The PNG.
    pub png: std::path::PathBuf,
    /// The EXR, when asked for.
    pub exr: Option<std::path::PathBuf>,
}

/// The files of every tile of a wall for the outputs `png` (and `exr`), row-major.
pub fn tile_files(
    wall: &WallGeometry,
    png: &std::path::Path,
    exr: Option<&std::path::Path>,
) -> Vec<TileFiles> {
    (0..wall.tiles())
        .map(|t| {
            let (c, r) = wall.tile_cr(t);
            TileFiles {
                png: tile_path(png, c, r),
                exr: exr.map(|e| tile_path(e, c, r)),
            }
        })
        .collect()
}

/// Where stacked-image pixels lie on the frustum's image plane. A plain image is one tile
/// of its own size (`cols = 1`, `tile_h = height`), and the map is the identity.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TileMap {
    /// Tile columns of the wall.
    pub cols: u32,
    /// Tile height (rows of the stacked image per tile).
    pub tile_h: u32,
    /// Plane pixels from one tile column to the next (`tile_w + mullion_x`).
    pub pitch_x: u32,
    /// Plane pixels from one tile row to the next (`tile_h + mullion_y`).
    pub pitch_y: u32,
}

impl TileMap {
    /// The identity map of a plain `width × height` image.
    pub fn plain(width: u32, height: u32) -> TileMap {
        TileMap {
            cols: 1,
            tile_h: height.max(1),
            pitch_x: width,
            pitch_y: height,
        }
    }

    /// Whether the map is the identity.
    pub fn is_plain(&self) -> bool {
        self.cols == 1 && self.pitch_y == self.tile_h
    }

    /// The plane pixel of stacked pixel `(x, y)`.
    #[inline]
    pub fn to_plane(&self, x: u32, y: u32) -> (u32, u32) {
        let t = y / self.tile_h;
        let (c, r) = (t % self.cols, t / self.cols);
        (
            c * self.pitch_x + x,
            r * self.pitch_y + (y - t * self.tile_h),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall() -> WallGeometry {
        WallGeometry {
            cols: 3,
            rows: 2,
            tile_w: 5,
            tile_h: 4,
            mullion_x: 2,
            mullion_y: 1,
        }
    }

    #[test]
    fn plane_stacked_and_tile_origins() {
        let w = wall();
        w.check().unwrap();
        assert_eq!(w.plane_size(), (3 * 5 + 2 * 2, 2 * 4 + 1));
        assert_eq!(w.stacked_size(), (5, 24));
        assert_eq!(w.tile_origin(0), (0, 0));
        assert_eq!(w.tile_origin(2), (14, 0));
        assert_eq!(w.tile_origin(4), (7, 5));
        assert_eq!(w.tile_span(4), (80, 100));
    }

    #[test]
    fn stacked_pixels_cover_the_plane_less_the_mullions_once() {
        let w = wall();
        let m = w.tile_map();
        let (pw, ph) = w.plane_size();
        let (sw, sh) = w.stacked_size();
        let mut hit = vec![0u8; (pw * ph) as usize];
        for y in 0..sh {
            for x in 0..sw {
                let (px, py) = m.to_plane(x, y);
                assert!(px < pw && py < ph);
                hit[(py * pw + px) as usize] += 1;
                let t = y / w.tile_h;
                let (ox, oy) = w.tile_origin(t);
                assert_eq!((px, py), (ox + x, oy + y % w.tile_h));
            }
        }
        for py in 0..ph {
            for px in 0..pw {
                let in_mullion = px % 7 >= 5 || py % 5 >= 4;
                assert_eq!(
                    hit[(py * pw + px) as usize],
                    u8::from(!in_mullion),
                    "({px}, {py})"
                );
            }
        }
        let p = TileMap::plain(9, 7);
        assert!(p.is_plain());
        assert!(!m.is_plain());
        for y in 0..7 {
            for x in 0..9 {
                assert_eq!(p.to_plane(x, y), (x, y));
            }
        }
    }

    #[test]
    fn drivers_default_consecutive_and_checked() {
        let w = wall();
        assert_eq!(w.default_drivers(2), [0, 0, 0, 1, 1, 1]);
        assert_eq!(w.default_drivers(4), [0, 0, 1, 2, 2, 3]);
        assert_eq!(w.default_drivers(12), [0, 2, 4, 6, 8, 10]);
        for n in 1..20 {
            let d = w.default_drivers(n);
            w.check_drivers(&d, n).unwrap();
            let spans = w.driver_spans(&d, n);
            let mut covered: Vec<(u32, u32)> =
                spans.iter().copied().filter(|s| s.0 < s.1).collect();
            covered.sort();
            assert_eq!(covered.first().unwrap().0, 0);
            assert_eq!(covered.last().unwrap().1, 6 * 20);
            for p in covered.windows(2) {
                assert_eq!(p[0].1, p[1].0);
            }
        }
        assert!(matches!(
            w.check_drivers(&[0, 1, 0, 1, 1, 1], 2),
            Err(WallError::NotConsecutive {
                rank: 0,
                first: 0,
                between: 1,
                later: 2
            })
        ));
        assert!(matches!(
            w.check_drivers(&[0, 0, 0, 1, 1, 2], 2),
            Err(WallError::RankRange {
                tile: 5,
                rank: 2,
                workers: 2
            })
        ));
        assert!(matches!(
            w.check_drivers(&[0, 0], 2),
            Err(WallError::RankCount { got: 2, tiles: 6 })
        ));
    }

    #[test]
    fn tile_names() {
        use std::path::Path;
        assert_eq!(
            tile_path(Path::new("out/f.png"), 2, 1),
            Path::new("out/f_c2r1.png")
        );
        assert_eq!(
            tile_path(Path::new("frames/frame_00007.exr"), 0, 0),
            Path::new("frames/frame_00007_c0r0.exr")
        );
        assert_eq!(tile_path(Path::new("wall"), 1, 3), Path::new("wall_c1r3"));
    }

    #[test]
    fn bad_layouts_are_refused() {
        let mut w = wall();
        w.cols = 0;
        assert!(w.check().unwrap_err().contains("wall.tiles"));
        let mut w = wall();
        w.tile_w = 40000;
        assert!(w.check().unwrap_err().contains("wall.tile_size"));
        let w = WallGeometry {
            cols: 64,
            rows: 64,
            tile_w: 32768,
            tile_h: 32768,
            mullion_x: 0,
            mullion_y: 0,
        };
        assert!(w.check().unwrap_err().contains("at most"));
    }
}
