//! Level and brick arithmetic of a multi-resolution page tree.
//!
//! A data set of `dims` samples is cut into pages of `page` samples per axis *including* a
//! border of `border` samples on each side that is copied from the neighbours at the same
//! level (Lux §3.3.2). The part a page owns, its *core*, is `C = page − 2·border` per axis.
//! Every level has the same page size; level `l + 1` has `ceil(dims_l / 2)` samples per
//! axis and is filtered 2×2(×2) from level `l`, so a page of level `l + 1` covers the cores
//! of up to 2×2(×2) pages of level `l`. The root level has a single page.
//!
//! Unlike Lux's cubic tree over the largest axis, each level's brick grid is exactly
//! `ceil(dims_l / C)` per axis, so non-power-of-two and very flat surveys waste nothing:
//! padding is virtual and never stored. A page at the data set's edge stores a full page;
//! the samples it holds outside the data set are edge replicas (volumes, so trilinear
//! sampling clamps to the edge) or holes (horizons: there is no surface beyond the grid).
//!
//! Volumes are octrees (`Dim::Three`); horizons are quadtrees (`Dim::Two`) whose z extent is 1
//! and which have no border in z.

use crate::ids::{
    morton2_decode, morton2_encode, morton3_decode, morton3_encode, PageId, MAX_BRICKS_PER_AXIS_3D,
    MAX_TILES_PER_AXIS_2D,
};
use serde::{Deserialize, Serialize};

/// Whether a tree is an octree of bricks or a quadtree of tiles.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Dim {
    /// Quadtree over (x, y); z is 1.
    Two,
    /// Octree over (x, y, z).
    Three,
}

/// Why a pyramid cannot be laid out.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PyramidError {
    /// A dimension is zero.
    #[error("dimensions must be at least 1 sample per axis, got {0:?}")]
    EmptyDims([u64; 3]),
    /// A 2D tree has z ≠ 1.
    #[error("a horizon grid has z extent 1, got {0}")]
    FlatZ(u64),
    /// The page size leaves no core.
    #[error("page size {page} with border {border} leaves no core (need page > 2·border)")]
    NoCore {
        /// Page size.
        page: u32,
        /// Border.
        border: u32,
    },
    /// A page too large to allocate for (a crafted or corrupt header).
    #[error("page size {page} exceeds the largest supported, {max} samples per axis")]
    PageTooLarge {
        /// Page size.
        page: u32,
        /// Largest allowed.
        max: u32,
    },
    /// More pages in all levels than a store or page table may index (a crafted or corrupt
    /// header: the index would be allocated before its checksum is read).
    #[error(
        "{pages} pages in all levels exceed the largest supported, {max} (larger pages hold more)"
    )]
    TooManyPages {
        /// Pages the layout needs.
        pages: u64,
        /// Largest allowed.
        max: u64,
    },
    /// Too many bricks for the id's Morton field.
    #[error("{bricks} pages along one axis exceed the page-id limit of {limit}")]
    TooManyBricks {
        /// Bricks needed.
        bricks: u64,
        /// Limit.
        limit: u64,
    },
}

/// Most pages of one pyramid, all levels: 2^28 (64³ pages of u8 samples: 64 TiB; its store
/// index 10 GiB). The page table's entries are `u32`.
pub const MAX_TOTAL_PAGES: u64 = 1 << 28;

/// Largest brick edge of a volume page (256³ f32 = 64 MiB).
pub const MAX_PAGE_3D: u32 = 256;
/// Largest tile edge of a horizon page (4096² f32 = 64 MiB).
pub const MAX_PAGE_2D: u32 = 4096;

/// One level of the tree.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct Level {
    /// Samples per axis at this level.
    pub dims: [u64; 3],
    /// Pages per axis at this level.
    pub bricks: [u32; 3],
}

impl Level {
    /// Number of pages in this level.
    pub fn page_count(&self) -> u64 {
        self.bricks.iter().map(|&b| b as u64).product()
    }
}

/// The layout of a multi-resolution tree: levels, page size, border.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Pyramid {
    dim: Dim,
    page: u32,
    border: u32,
    levels: Vec<Level>,
}

fn ceil_div(a: u64, b: u64) -> u64 {
    a.div_ceil(b)
}

impl Pyramid {
    /// Lays out the tree for `dims` samples with pages of `page` samples per axis (border included).
    pub fn new(dim: Dim, dims: [u64; 3], page: u32, border: u32) -> Result<Self, PyramidError> {
        if dims.contains(&0) {
            return Err(PyramidError::EmptyDims(dims));
        }
        if dim == Dim::Two && dims[2] != 1 {
            return Err(PyramidError::FlatZ(dims[2]));
        }
        // Bounded before anything is sized from it: caches, atlas slots and decoders
        // allocate whole pages (at most 64 MiB of f32 either way).
        let max = match dim {
            Dim::Two => MAX_PAGE_2D,
            Dim::Three => MAX_PAGE_3D,
        };
        if page > max {
            return Err(PyramidError::PageTooLarge { page, max });
        }
        // In u64: `2 * border` of a u32 read from a file can wrap to 0.
        if page as u64 <= 2 * border as u64 {
            return Err(PyramidError::NoCore { page, border });
        }
        let core = (page - 2 * border) as u64;
        let limit = match dim {
            Dim::Two => MAX_TILES_PER_AXIS_2D,
            Dim::Three => MAX_BRICKS_PER_AXIS_3D,
        } as u64;
        let mut levels = Vec::new();
        let mut d = dims;
        loop {
            let mut bricks = [1u32; 3];
            for a in 0..3 {
                if dim == Dim::Two && a == 2 {
                    continue;
                }
                let b = ceil_div(d[a], core);
                if b > limit {
                    return Err(PyramidError::TooManyBricks { bricks: b, limit });
                }
                bricks[a] = b as u32;
            }
            levels.push(Level { dims: d, bricks });
            let pages: u64 = levels.iter().map(Level::page_count).sum();
            if pages > MAX_TOTAL_PAGES {
                return Err(PyramidError::TooManyPages {
                    pages,
                    max: MAX_TOTAL_PAGES,
                });
            }
            if bricks == [1, 1, 1] {
                break;
            }
            for a in 0..3 {
                if !(dim == Dim::Two && a == 2) {
                    d[a] = ceil_div(d[a], 2);
                }
            }
        }
        Ok(Pyramid {
            dim,
            page,
            border,
            levels,
        })
    }

    /// Octree or quadtree.
    pub fn dim(&self) -> Dim {
        self.dim
    }
    /// Page size per axis, border included.
    pub fn page(&self) -> u32 {
        self.page
    }
    /// Border per side.
    pub fn border(&self) -> u32 {
        self.border
    }
    /// Core samples per axis (`page − 2·border`).
    pub fn core(&self) -> u32 {
        self.page - 2 * self.border
    }
    /// Number of levels (level 0 finest, the last is the single-page root).
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }
    /// All levels.
    pub fn levels(&self) -> &[Level] {
        &self.levels
    }
    /// One level.
    pub fn level(&self, l: usize) -> &Level {
        &self.levels[l]
    }
    /// Page extent in samples per axis: `[P, P, P]` or `[P, P, 1]`.
    pub fn page_dims(&self) -> [u32; 3] {
        match self.dim {
            Dim::Two => [self.page, self.page, 1],
            Dim::Three => [self.page; 3],
        }
    }
    /// Samples per page.
    pub fn page_samples(&self) -> usize {
        self.page_dims().iter().map(|&d| d as usize).product()
    }
    /// Border per axis (`[b, b, 0]` for quadtrees).
    pub fn border3(&self) -> [u32; 3] {
        match self.dim {
            Dim::Two => [self.border, self.border, 0],
            Dim::Three => [self.border; 3],
        }
    }
    /// Core extent per axis (`[C, C, 1]` for quadtrees).
    pub fn core3(&self) -> [u32; 3] {
        match self.dim {
            Dim::Two => [self.core(), self.core(), 1],
            Dim::Three => [self.core(); 3],
        }
    }
    /// Level-`l` sample coordinate of the first sample of a page (its border included);
    /// negative at the data set's low edge.
    pub fn page_origin(&self, brick: [u32; 3]) -> [i64; 3] {
        let (c, b) = (self.core3(), self.border3());
        [0, 1, 2].map(|a| brick[a] as i64 * c[a] as i64 - b[a] as i64)
    }
    /// The half-open range of level samples a page owns (its core), clipped to the level.
    pub fn core_range(&self, level: usize, brick: [u32; 3]) -> [(u64, u64); 3] {
        let c = self.core3();
        let d = self.levels[level].dims;
        [0, 1, 2].map(|a| {
            let lo = brick[a] as u64 * c[a] as u64;
            (lo, (lo + c[a] as u64).min(d[a]))
        })
    }
    /// Morton index of a brick within its level.
    pub fn morton(&self, brick: [u32; 3]) -> u64 {
        match self.dim {
            Dim::Two => morton2_encode(brick[0], brick[1]),
            Dim::Three => morton3_encode(brick[0], brick[1], brick[2]),
        }
    }
    /// Brick coordinates of a Morton index.
    pub fn brick_of(&self, morton: u64) -> [u32; 3] {
        match self.dim {
            Dim::Two => {
                let [x, y] = morton2_decode(morton);
                [x, y, 0]
            }
            Dim::Three => morton3_decode(morton),
        }
    }
    /// Whether a brick lies inside the level's grid.
    pub fn contains(&self, level: usize, brick: [u32; 3]) -> bool {
        level < self.levels.len() && (0..3).all(|a| brick[a] < self.levels[level].bricks[a])
    }
    /// The page id (data set 0) of a brick.
    pub fn id(&self, level: usize, brick: [u32; 3]) -> PageId {
        PageId::new(0, level as u8, self.morton(brick))
    }
    /// The parent brick one level up, or `None` at the root.
    pub fn parent(&self, level: usize, brick: [u32; 3]) -> Option<[u32; 3]> {
        (level + 1 < self.levels.len()).then(|| brick.map(|b| b >> 1))
    }
    /// The children one level down that exist (edge pages have fewer than 2^d).
    pub fn children(&self, level: usize, brick: [u32; 3]) -> Vec<[u32; 3]> {
        if level == 0 {
            return Vec::new();
        }
        let zs: &[u32] = if self.dim == Dim::Two { &[0] } else { &[0, 1] };
        let mut out = Vec::with_capacity(8);
        for &dz in zs {
            for dy in 0..2 {
                for dx in 0..2 {
                    let c = [
                        brick[0] * 2 + dx,
                        brick[1] * 2 + dy,
                        if self.dim == Dim::Two {
                            0
                        } else {
                            brick[2] * 2 + dz
                        },
                    ];
                    if self.contains(level - 1, c) {
                        out.push(c);
                    }
                }
            }
        }
        out
    }
    /// All bricks of a level in Z-order (the order of the on-disk index).
    pub fn bricks_in_z_order(&self, level: usize) -> Vec<[u32; 3]> {
        let b = self.levels[level].bricks;
        let mut v: Vec<(u64, [u32; 3])> =
            Vec::with_capacity(self.levels[level].page_count() as usize);
        for z in 0..b[2] {
            for y in 0..b[1] {
                for x in 0..b[0] {
                    let br = [x, y, z];
                    v.push((self.morton(br), br));
                }
            }
        }
        v.sort_unstable_by_key(|e| e.0);
        v.into_iter().map(|e| e.1).collect()
    }
    /// Total pages over all levels.
    pub fn total_pages(&self) -> u64 {
        self.levels.iter().map(Level::page_count).sum()
    }
    /// Fraction of a page that is border: `1 − (C/P)^d` (Lux Table 3.1, corrected).
    pub fn border_overhead(&self) -> f64 {
        let r = self.core() as f64 / self.page as f64;
        match self.dim {
            Dim::Two => 1.0 - r * r,
            Dim::Three => 1.0 - r * r * r,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn lux_example_depth() {
        // Lux §3.3.2: 5989 voxels, 64³ pages (C = 62) → 97 bricks → 8 levels (depth 7) with a cubic tree.
        let p = Pyramid::new(Dim::Three, [5989, 5989, 5989], 64, 1).unwrap();
        assert_eq!(p.level(0).bricks, [97, 97, 97]);
        assert_eq!(p.level_count(), 8);
        assert_eq!(p.levels().last().unwrap().bricks, [1, 1, 1]);
    }

    #[test]
    fn overhead_matches_corrected_table() {
        let p = Pyramid::new(Dim::Three, [64, 64, 64], 64, 1).unwrap();
        assert!((p.border_overhead() - 0.0909).abs() < 1e-3);
        let p = Pyramid::new(Dim::Three, [64, 64, 64], 32, 1).unwrap();
        assert!((p.border_overhead() - 0.176).abs() < 1e-3);
        let p = Pyramid::new(Dim::Two, [64, 64, 1], 128, 2).unwrap();
        assert!((p.border_overhead() - 0.0623).abs() < 1e-3);
    }

    #[test]
    fn rejects_bad_layouts() {
        assert!(matches!(
            Pyramid::new(Dim::Three, [0, 4, 4], 64, 1),
            Err(PyramidError::EmptyDims(_))
        ));
        assert!(matches!(
            Pyramid::new(Dim::Three, [4, 4, 4], 2, 1),
            Err(PyramidError::NoCore { .. })
        ));
        // A border whose double wraps a u32 to 0 (a store header's field) has no core
        // either.
        assert!(matches!(
            Pyramid::new(Dim::Three, [4, 4, 4], 64, 1 << 31),
            Err(PyramidError::NoCore { .. })
        ));
        assert!(matches!(
            Pyramid::new(Dim::Two, [4, 4, 2], 64, 1),
            Err(PyramidError::FlatZ(2))
        ));
        assert!(matches!(
            Pyramid::new(Dim::Three, [u32::MAX as u64, 4, 4], 64, 1),
            Err(PyramidError::TooManyBricks { .. })
        ));
        // Within the per-axis limit but 2^42 pages in all: its index alone would take
        // 160 TiB, read from a sparse file before the checksum could refuse it.
        let max = MAX_BRICKS_PER_AXIS_3D as u64 * 62;
        assert!(matches!(
            Pyramid::new(Dim::Three, [max, max, max], 64, 1),
            Err(PyramidError::TooManyPages { .. })
        ));
        assert!(matches!(
            Pyramid::new(Dim::Two, [1 << 20, 1 << 20, 1], 66, 1),
            Err(PyramidError::TooManyPages { .. })
        ));
        assert!(Pyramid::new(Dim::Three, [62 * 512, 62 * 512, 62 * 512], 64, 1).is_ok());
        // Untrusted page sizes are bounded before anything allocates a page (a crafted
        // header once asked for u32::MAX³ samples).
        for (dim, page) in [(Dim::Three, 257), (Dim::Three, u32::MAX), (Dim::Two, 4097)] {
            let dims = if dim == Dim::Two {
                [8, 8, 1]
            } else {
                [8, 8, 8]
            };
            assert!(
                matches!(
                    Pyramid::new(dim, dims, page, 1),
                    Err(PyramidError::PageTooLarge { .. })
                ),
                "{page}"
            );
        }
        assert!(Pyramid::new(Dim::Three, [8, 8, 8], 256, 1).is_ok());
        assert!(Pyramid::new(Dim::Two, [8, 8, 1], 4096, 1).is_ok());
    }

    proptest! {
        /// Cores of one level tile the level exactly: every sample is owned by exactly one page.
        #[test]
        fn cores_tile_each_level(nx in 1u64..300, ny in 1u64..300, nz in 1u64..300, ps in prop::sample::select(vec![8u32, 16, 32, 64]), b in 1u32..3) {
            let p = Pyramid::new(Dim::Three, [nx, ny, nz], ps, b).unwrap();
            for (l, lev) in p.levels().iter().enumerate() {
                for a in 0..3 {
                    let mut covered = 0u64;
                    for i in 0..lev.bricks[a] {
                        let mut br = [0u32; 3];
                        br[a] = i;
                        let r = p.core_range(l, br)[a];
                        prop_assert_eq!(r.0, covered);
                        prop_assert!(r.1 > r.0);
                        covered = r.1;
                    }
                    prop_assert_eq!(covered, lev.dims[a]);
                }
                if l + 1 < p.level_count() {
                    prop_assert_eq!(p.level(l + 1).dims, lev.dims.map(|d| d.div_ceil(2)));
                }
            }
            prop_assert_eq!(p.levels().last().unwrap().bricks, [1, 1, 1]);
        }

        /// Parent and child relations agree, and a parent's core covers its children's cores.
        #[test]
        fn parent_child_consistent(nx in 1u64..500, ny in 1u64..500, nz in 1u64..100) {
            let p = Pyramid::new(Dim::Three, [nx, ny, nz], 16, 1).unwrap();
            for l in 1..p.level_count() {
                for br in p.bricks_in_z_order(l) {
                    for ch in p.children(l, br) {
                        prop_assert_eq!(p.parent(l - 1, ch), Some(br));
                        let pr = p.core_range(l, br);
                        let cr = p.core_range(l - 1, ch);
                        for a in 0..3 {
                            prop_assert!(cr[a].0 >= 2 * pr[a].0 && cr[a].1 <= 2 * pr[a].1);
                        }
                    }
                }
            }
            // Every page below the root has a parent that exists.
            for l in 0..p.level_count() - 1 {
                for br in p.bricks_in_z_order(l) {
                    let par = p.parent(l, br).unwrap();
                    prop_assert!(p.contains(l + 1, par));
                }
            }
        }

        #[test]
        fn z_order_ids_are_sorted_and_unique(nx in 1u64..2000, ny in 1u64..2000) {
            let p = Pyramid::new(Dim::Two, [nx, ny, 1], 128, 2).unwrap();
            for l in 0..p.level_count() {
                let ids: Vec<_> = p.bricks_in_z_order(l).into_iter().map(|b| p.id(l, b)).collect();
                prop_assert!(ids.windows(2).all(|w| w[0] < w[1]));
                for (i, b) in p.bricks_in_z_order(l).into_iter().enumerate() {
                    prop_assert_eq!(p.brick_of(ids[i].morton()), b);
                }
            }
        }
    }
}
