//! Unified page ids and Morton (Z-order) codes.
//!
//! A page id is one `u64`: `data set (16 bits) | level (6 bits) | Morton index (42 bits)`.
//! Lux's dissertation packed ids into 32 bits (8-bit instance, 24-bit index), which limits
//! octrees to depth 7; its own 109 GiB volume needed depth 9 (digest §2.4, erratum). With
//! 42 bits of Morton index an octree level addresses 2^14 bricks per axis (about a million
//! samples per axis with 64³ bricks) and a quadtree level 2^21 tiles per axis; a whole
//! pyramid holds at most `pyramid::MAX_TOTAL_PAGES` (2^28) pages, which binds before
//! the Morton field does: about 645 bricks per axis for a cubic volume, 2^14 tiles per axis
//! for a square horizon.
//!
//! Level 0 is the finest level (the source samples); level `levels - 1` is the root.
//! Ordering ids numerically orders pages by data set, then level, then Z-order, which is
//! the order of the on-disk index.

use bytemuck::{Pod, Zeroable};
use serde::{Deserialize, Serialize};

/// Bits of the data-set field.
pub const DATASET_BITS: u32 = 16;
/// Bits of the level field.
pub const LEVEL_BITS: u32 = 6;
/// Bits of the Morton field.
pub const MORTON_BITS: u32 = 42;
/// Largest brick coordinate + 1 per axis that an octree page id can hold.
pub const MAX_BRICKS_PER_AXIS_3D: u32 = 1 << (MORTON_BITS / 3);
/// Largest tile coordinate + 1 per axis that a quadtree page id can hold.
pub const MAX_TILES_PER_AXIS_2D: u32 = 1 << (MORTON_BITS / 2);

const MORTON_MASK: u64 = (1 << MORTON_BITS) - 1;
const LEVEL_MASK: u64 = (1 << LEVEL_BITS) - 1;

/// A unified page id: data set, level and Morton index in one `u64`.
#[repr(transparent)]
#[derive(
    Copy,
    Clone,
    Debug,
    Default,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Pod,
    Zeroable,
    Serialize,
    Deserialize,
)]
pub struct PageId(pub u64);

impl PageId {
    /// Packs the three fields. Panics in debug builds if a field is out of range; callers
    /// derive the fields from a validated [`crate::pyramid::Pyramid`].
    pub fn new(dataset: u16, level: u8, morton: u64) -> Self {
        debug_assert!((level as u64) <= LEVEL_MASK && morton <= MORTON_MASK);
        PageId(
            ((dataset as u64) << (LEVEL_BITS + MORTON_BITS))
                | (((level as u64) & LEVEL_MASK) << MORTON_BITS)
                | (morton & MORTON_MASK),
        )
    }
    /// The data-set field.
    pub fn dataset(self) -> u16 {
        (self.0 >> (LEVEL_BITS + MORTON_BITS)) as u16
    }
    /// The level field (0 = finest).
    pub fn level(self) -> u8 {
        ((self.0 >> MORTON_BITS) & LEVEL_MASK) as u8
    }
    /// The Morton index within the level.
    pub fn morton(self) -> u64 {
        self.0 & MORTON_MASK
    }
    /// The same page in another data set (stores are written with data set 0; a worker
    /// assigns data-set numbers when it opens several stores).
    pub fn with_dataset(self, dataset: u16) -> Self {
        PageId::new(dataset, self.level(), self.morton())
    }
}

impl std::fmt::Display for PageId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "page {}/L{}/m{}",
            self.dataset(),
            self.level(),
            self.morton()
        )
    }
}

/// Spreads the low 21 bits of `v` so that there are two zero bits between each.
#[inline]
fn part1by2(v: u32) -> u64 {
    let mut x = (v as u64) & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

#[inline]
fn compact1by2(v: u64) -> u32 {
    let mut x = v & 0x1249_2492_4924_9249;
    x = (x | (x >> 2)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x >> 4)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x >> 8)) & 0x001f_0000_ff00_00ff;
    x = (x | (x >> 16)) & 0x001f_0000_0000_ffff;
    x = (x | (x >> 32)) & 0x1f_ffff;
    x as u32
}

/// Spreads the low 32 bits of `v` so that there is one zero bit between each.
#[inline]
fn part1by1(v: u32) -> u64 {
    let mut x = v as u64;
    x = (x | (x << 16)) & 0x0000_ffff_0000_ffff;
    x = (x | (x << 8)) & 0x00ff_00ff_00ff_00ff;
    x = (x | (x << 4)) & 0x0f0f_0f0f_0f0f_0f0f;
    x = (x | (x << 2)) & 0x3333_3333_3333_3333;
    x = (x | (x << 1)) & 0x5555_5555_5555_5555;
    x
}

#[inline]
fn compact1by1(v: u64) -> u32 {
    let mut x = v & 0x5555_5555_5555_5555;
    x = (x | (x >> 1)) & 0x3333_3333_3333_3333;
    x = (x | (x >> 2)) & 0x0f0f_0f0f_0f0f_0f0f;
    x = (x | (x >> 4)) & 0x00ff_00ff_00ff_00ff;
    x = (x | (x >> 8)) & 0x0000_ffff_0000_ffff;
    x = (x | (x >> 16)) & 0x0000_0000_ffff_ffff;
    x as u32
}

/// 3D Morton code of `(x, y, z)`, each below 2^21. x is the least significant bit.
#[inline]
pub fn morton3_encode(x: u32, y: u32, z: u32) -> u64 {
    part1by2(x) | (part1by2(y) << 1) | (part1by2(z) << 2)
}

/// Inverse of [`morton3_encode`].
#[inline]
pub fn morton3_decode(m: u64) -> [u32; 3] {
    [compact1by2(m), compact1by2(m >> 1), compact1by2(m >> 2)]
}

/// 2D Morton code of `(x, y)`. x is the least significant bit.
#[inline]
pub fn morton2_encode(x: u32, y: u32) -> u64 {
    part1by1(x) | (part1by1(y) << 1)
}

/// Inverse of [`morton2_encode`].
#[inline]
pub fn morton2_decode(m: u64) -> [u32; 2] {
    [compact1by1(m), compact1by1(m >> 1)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn morton_known_values() {
        assert_eq!(morton3_encode(1, 0, 0), 1);
        assert_eq!(morton3_encode(0, 1, 0), 2);
        assert_eq!(morton3_encode(0, 0, 1), 4);
        assert_eq!(morton3_encode(3, 3, 3), 63);
        assert_eq!(morton2_encode(1, 1), 3);
        assert_eq!(morton2_encode(2, 0), 4);
    }

    proptest! {
        #[test]
        fn morton3_round_trip(x in 0u32..(1 << 21), y in 0u32..(1 << 21), z in 0u32..(1 << 21)) {
            prop_assert_eq!(morton3_decode(morton3_encode(x, y, z)), [x, y, z]);
        }

        #[test]
        fn morton2_round_trip(x: u32, y: u32) {
            prop_assert_eq!(morton2_decode(morton2_encode(x, y)), [x, y]);
        }

        /// The parent of a node is the node whose Morton code is the child's shifted by the
        /// dimension: Z-order keeps siblings contiguous, which is what makes the on-disk order useful.
        #[test]
        fn morton3_parent_is_shift(x in 0u32..(1 << 14), y in 0u32..(1 << 14), z in 0u32..(1 << 14)) {
            prop_assert_eq!(morton3_encode(x, y, z) >> 3, morton3_encode(x >> 1, y >> 1, z >> 1));
        }

        #[test]
        fn morton_order_is_monotone_in_each_axis(x in 0u32..(1 << 14) - 1, y in 0u32..(1 << 14) - 1, z in 0u32..(1 << 14) - 1) {
            prop_assert!(morton3_encode(x + 1, y, z) > morton3_encode(x, y, z));
            prop_assert!(morton3_encode(x, y + 1, z) > morton3_encode(x, y, z));
            prop_assert!(morton3_encode(x, y, z + 1) > morton3_encode(x, y, z));
        }

        #[test]
        fn page_id_fields_round_trip(ds: u16, level in 0u8..64, m in 0u64..(1u64 << 42)) {
            let id = PageId::new(ds, level, m);
            prop_assert_eq!(id.dataset(), ds);
            prop_assert_eq!(id.level(), level);
            prop_assert_eq!(id.morton(), m);
            prop_assert_eq!(id.with_dataset(7).morton(), m);
        }

        #[test]
        fn page_id_order_is_dataset_level_morton(a in (0u16..4, 0u8..8, 0u64..1000), b in (0u16..4, 0u8..8, 0u64..1000)) {
            let ia = PageId::new(a.0, a.1, a.2);
            let ib = PageId::new(b.0, b.1, b.2);
            prop_assert_eq!(ia.cmp(&ib), a.cmp(&b));
        }
    }
}
