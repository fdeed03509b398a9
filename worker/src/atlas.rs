//! The virtualized atlas: a fixed pool of physical page slots plus per-data-set page tables.
//!
//! Everything the ray caster reads is a flat `#[repr(C)]` array, laid out exactly as the
//! wgpu caster uploads it:
//!
//! * the **pool**: `slots × page_samples` f32 (page samples x fastest, border included);
//! * **slot records** ([`SlotInfo`]): which page a slot holds and when it was last used;
//! * **page tables**: one `u32` per virtual page of every level of a data set, concatenated
//!   level by level (level 0 first, bricks x fastest), with per-level offsets and brick
//!   counts in [`LevelInfo`]. An entry is `slot | level << 24`: the slot of the page itself
//!   if resident, otherwise of its nearest resident ancestor and that ancestor's level.
//!   [`NOT_RESIDENT`] marks a page with no resident ancestor (never the case once a data
//!   set's root is pinned).
//!
//! One pool holds volume bricks and another horizon tiles, each with its own budget.

use bytemuck::{Pod, Zeroable};
use std::collections::{HashMap, HashSet};
use strata_common::ids::PageId;
use strata_common::pyramid::Pyramid;

/// Page-table entry for "nothing resident on the path to the root".
pub const NOT_RESIDENT: u32 = u32::MAX;
/// Bits of a page-table entry that hold the slot.
pub const SLOT_MASK: u32 = (1 << 24) - 1;
/// Largest number of slots a pool may have.
pub const MAX_SLOTS: usize = SLOT_MASK as usize;

/// One slot's record.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct SlotInfo {
    /// Page key held, or `u64::MAX` when free.
    pub page: u64,
    /// Frame number of the last use.
    pub last_used: u32,
    /// 1 = pinned (a data set's root; never evicted).
    pub pinned: u32,
}

/// Per-level layout of a page table.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct LevelInfo {
    /// First entry of this level in `entries`.
    pub offset: u32,
    /// Bricks per axis.
    pub bricks: [u32; 3],
}

/// A data set's page table.
#[derive(Clone, Debug)]
pub struct PageTable {
    /// Per level.
    pub levels: Vec<LevelInfo>,
    /// Entries, see the module docs.
    pub entries: Vec<u32>,
}

impl PageTable {
    /// An empty table for a pyramid.
    pub fn new(p: &Pyramid) -> Self {
        let mut levels = Vec::new();
        let mut n = 0u32;
        for l in p.levels() {
            levels.push(LevelInfo {
                offset: n,
                bricks: l.bricks,
            });
            n += l.bricks.iter().product::<u32>();
        }
        PageTable {
            levels,
            entries: vec![NOT_RESIDENT; n as usize],
        }
    }

    /// Entry index of `(level, brick)`.
    #[inline(always)]
    pub fn index(&self, level: usize, b: [u32; 3]) -> usize {
        let li = &self.levels[level];
        li.offset as usize + ((b[2] * li.bricks[1] + b[1]) * li.bricks[0] + b[0]) as usize
    }

    /// Fills every entry from the set of resident pages (`slot_of(level, brick)`), top-down
    /// so each page inherits its parent's entry when it is not resident itself.
    pub fn rebuild(&mut self, mut slot_of: impl FnMut(usize, [u32; 3]) -> Option<u32>) {
        let nl = self.levels.len();
        for level in (0..nl).rev() {
            let li = self.levels[level];
            for z in 0..li.bricks[2] {
                for y in 0..li.bricks[1] {
                    for x in 0..li.bricks[0] {
                        let b = [x, y, z];
                        let e = match slot_of(level, b) {
                            Some(s) => s | (level as u32) << 24,
                            None if level + 1 < nl => {
                                self.entries[self.index(level + 1, [x / 2, y / 2, z / 2])]
                            }
                            None => NOT_RESIDENT,
                        };
                        let i = self.index(level, b);
                        self.entries[i] = e;
                    }
                }
            }
        }
    }
}

/// A pool of page slots.
#[derive(Debug)]
pub struct Pool {
    /// Samples per page (border included).
    pub page_samples: usize,
    /// `slots × page_samples` samples.
    pub data: Vec<f32>,
    /// Slot records.
    pub slots: Vec<SlotInfo>,
    map: HashMap<u64, u32>,
    free: Vec<u32>,
}

/// Why a page could not be placed.
#[derive(Debug, PartialEq, Eq)]
pub enum PlaceError {
    /// Every slot holds a page that is pinned or needed by the current frame.
    Full,
}

impl Pool {
    /// A pool of `budget_bytes / page bytes` slots (at least one).
    pub fn new(page_samples: usize, budget_bytes: u64) -> Self {
        let n = ((budget_bytes / (page_samples as u64 * 4)) as usize).clamp(1, MAX_SLOTS);
        Pool {
            page_samples,
            data: vec![0.0; n * page_samples],
            slots: vec![
                SlotInfo {
                    page: u64::MAX,
                    ..SlotInfo::default()
                };
                n
            ],
            map: HashMap::new(),
            free: (0..n as u32).rev().collect(),
        }
    }

    /// Number of slots.
    pub fn capacity(&self) -> usize {
        self.slots.len()
    }

    /// Slots in use.
    pub fn used(&self) -> usize {
        self.map.len()
    }

    /// The slot holding `key`.
    pub fn slot_of(&self, key: u64) -> Option<u32> {
        self.map.get(&key).copied()
    }

    /// Marks a resident page as used in `frame`.
    pub fn touch(&mut self, key: u64, frame: u32) {
        if let Some(&s) = self.map.get(&key) {
            self.slots[s as usize].last_used = frame;
        }
    }

    /// Copies a page into a slot: a free one, or the least recently used one that is neither
    /// pinned nor in `keep`.
    pub fn place(
        &mut self,
        key: u64,
        samples: &[f32],
        frame: u32,
        pinned: bool,
        keep: &HashSet<u64>,
    ) -> Result<u32, PlaceError> {
        assert_eq!(samples.len(), self.page_samples);
        if let Some(&s) = self.map.get(&key) {
            return Ok(s);
        }
        let slot = match self.free.pop() {
            Some(s) => s,
            None => {
                let victim = self
                    .slots
                    .iter()
                    .enumerate()
                    .filter(|(_, s)| s.pinned == 0 && !keep.contains(&s.page))
                    .min_by_key(|(_, s)| s.last_used)
                    .map(|(i, _)| i as u32)
                    .ok_or(PlaceError::Full)?;
                let old = self.slots[victim as usize].page;
                self.map.remove(&old);
                victim
            }
        };
        let o = slot as usize * self.page_samples;
        self.data[o..o + self.page_samples].copy_from_slice(samples);
        self.slots[slot as usize] = SlotInfo {
            page: key,
            last_used: frame,
            pinned: pinned as u32,
        };
        self.map.insert(key, slot);
        Ok(slot)
    }

    /// The samples of a slot.
    #[inline(always)]
    pub fn slot_data(&self, slot: u32) -> &[f32] {
        let o = slot as usize * self.page_samples;
        &self.data[o..o + self.page_samples]
    }

    /// Resident pages of one data set, as a lookup for [`PageTable::rebuild`].
    pub fn resident_of(
        &self,
        dataset: u16,
        pyramid: &Pyramid,
    ) -> impl FnMut(usize, [u32; 3]) -> Option<u32> + '_ {
        let p = pyramid.clone();
        move |level, b| {
            let key = p.id(level, b).with_dataset(dataset).0;
            self.map.get(&key).copied()
        }
    }
}

/// The key of page `(level, brick)` of data set `dataset`.
pub fn page_key(dataset: u16, pyramid: &Pyramid, level: usize, brick: [u32; 3]) -> u64 {
    pyramid.id(level, brick).with_dataset(dataset).0
}

/// Decodes a page key into (data set, level, brick).
pub fn key_parts(key: u64, pyramid: &Pyramid) -> (u16, usize, [u32; 3]) {
    let id = PageId(key);
    (
        id.dataset(),
        id.level() as usize,
        pyramid.brick_of(id.morton()),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_common::pyramid::Dim;

    #[test]
    fn table_falls_back_to_nearest_resident_ancestor() {
        let p = Pyramid::new(Dim::Three, [100, 60, 30], 34, 1).unwrap(); // core 32
        let mut t = PageTable::new(&p);
        let top = p.level_count() - 1;
        // Root in slot 7, one level-0 brick in slot 3.
        t.rebuild(|l, b| {
            if l == top {
                Some(7)
            } else if l == 0 && b == [2, 1, 0] {
                Some(3)
            } else {
                None
            }
        });
        assert_eq!(t.entries[t.index(0, [2, 1, 0])], 3);
        assert_eq!(t.entries[t.index(0, [0, 0, 0])], 7 | (top as u32) << 24);
        assert_eq!(t.entries[t.index(1, [1, 0, 0])], 7 | (top as u32) << 24);
    }

    #[test]
    fn pool_evicts_lru_but_not_pinned_or_kept() {
        let mut pool = Pool::new(8, 8 * 4 * 3);
        assert_eq!(pool.capacity(), 3);
        let none = HashSet::new();
        pool.place(1, &[1.0; 8], 0, true, &none).unwrap();
        pool.place(2, &[2.0; 8], 1, false, &none).unwrap();
        pool.place(3, &[3.0; 8], 2, false, &none).unwrap();
        let keep: HashSet<u64> = [2].into();
        let s = pool.place(4, &[4.0; 8], 3, false, &keep).unwrap();
        assert_eq!(pool.slot_of(3), None, "3 was the only evictable page");
        assert_eq!(pool.slot_data(s), &[4.0; 8]);
        let keep: HashSet<u64> = [2, 4].into();
        assert_eq!(
            pool.place(5, &[5.0; 8], 4, false, &keep),
            Err(PlaceError::Full)
        );
    }
}
