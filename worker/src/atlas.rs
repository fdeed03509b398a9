//! The virtualized atlas: a fixed pool of physical page slots plus per-data-set page tables.
//!
//! Everything the ray casters read is a flat `#[repr(C)]` array whose records live in
//! [`strata_common::gpu`], so the CPU caster and the wgpu backend read one layout:
//!
//! * the **pool**: `slots × page_samples` samples (x fastest, border included). The CPU
//!   backend keeps them in host memory, in the volume's own sample type when every volume
//!   of the scene shares one and none has a no-data value (`render.compact_slots`; a `u8`
//!   volume then takes one byte per voxel), else as f32, with the value ranges of the
//!   slots' macrocells ([`crate::macrocell`]); the GPU backend keeps only the bookkeeping
//!   here ([`Pool::bookkeeping`]) and the samples on the device, slot for slot, in the
//!   data's own width (`strata_common::gpu::PoolFormat`: a storage buffer, or a 3D texture
//!   for `render.gpu_filter = "hardware"`);
//! * **slot records** ([`SlotInfo`]): which page a slot holds and when it was last used;
//! * **page tables**: one `u32` per virtual page of every level of a data set, concatenated
//!   level by level (level 0 first, bricks x fastest), with per-level offsets and brick
//!   counts in [`LevelInfo`]. An entry is `slot | level << 24`: the slot of the page itself
//!   if resident, otherwise of its nearest resident ancestor and that ancestor's level.
//!   [`NOT_RESIDENT`] marks a page with no resident ancestor (never the case once a data
//!   set's root is pinned). A resident horizon tile whose own cells are too broken up by
//!   holes to draw it at its level carries [`ENTRY_FRAGMENTED`] in its own entry (computed
//!   as it enters its slot; descendants that inherit the entry do not inherit the flag).
//!
//! One pool holds volume bricks and another horizon tiles, each with its own budget.

use crate::macrocell::MacroCells;
use std::collections::{HashMap, HashSet};
use strata_common::ids::PageId;
use strata_common::pyramid::Pyramid;
use strata_common::sample::SampleType;

pub use strata_common::gpu::{
    entry_level, LevelInfo, SlotInfo, ENTRY_FRAGMENTED, MAX_SLOTS, NOT_RESIDENT, SLOT_MASK,
};

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
        let mut n = 0u64;
        for l in p.levels() {
            levels.push(LevelInfo {
                offset: n as u32,
                bricks: l.bricks,
            });
            n += l.bricks.iter().map(|&b| b as u64).product::<u64>();
        }
        // Unreachable for a pyramid that was built: `Pyramid::new` refuses more than
        // `MAX_TOTAL_PAGES` (2^28) pages.
        assert!(
            n < u32::MAX as u64,
            "a page table of {n} entries does not fit u32 indices"
        );
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

    /// Fills every entry from the set of resident pages (`slot_of(level, brick)`: the slot,
    /// with [`ENTRY_FRAGMENTED`] where it applies), top-down so each page inherits its
    /// parent's entry, less the flag, when it is not resident itself.
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
                                match self.entries[self.index(level + 1, [x / 2, y / 2, z / 2])] {
                                    NOT_RESIDENT => NOT_RESIDENT,
                                    up => up & !ENTRY_FRAGMENTED,
                                }
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

/// A sample type a CPU pool can hold: its value is the `f32` the decoded page holds, exactly.
pub trait Voxel: Copy + Send + Sync + 'static {
    /// The element for a decoded value (an integer of the type's range, or any f32).
    fn from_value(v: f32) -> Self;
    /// The decoded value.
    fn value(self) -> f32;
}

macro_rules! int_voxel {
    ($($t:ty),*) => {$(
        impl Voxel for $t {
            #[inline(always)]
            fn from_value(v: f32) -> Self {
                v as $t
            }
            #[inline(always)]
            fn value(self) -> f32 {
                self as f32
            }
        }
    )*};
}
int_voxel!(u8, i8, u16, i16);

impl Voxel for f32 {
    #[inline(always)]
    fn from_value(v: f32) -> Self {
        v
    }
    #[inline(always)]
    fn value(self) -> f32 {
        self
    }
}

/// The samples of a CPU pool, in one element type.
#[derive(Debug)]
pub enum SlotData {
    /// Decoded `f32` (any volume; NaN = no data).
    F32(Vec<f32>),
    /// `u8` volumes.
    U8(Vec<u8>),
    /// `i8` volumes.
    I8(Vec<i8>),
    /// `u16` volumes.
    U16(Vec<u16>),
    /// `i16` volumes.
    I16(Vec<i16>),
}

/// A borrowed [`SlotData`].
#[derive(Copy, Clone, Debug)]
pub enum Samples<'a> {
    /// See [`SlotData::F32`].
    F32(&'a [f32]),
    /// See [`SlotData::U8`].
    U8(&'a [u8]),
    /// See [`SlotData::I8`].
    I8(&'a [i8]),
    /// See [`SlotData::U16`].
    U16(&'a [u16]),
    /// See [`SlotData::I16`].
    I16(&'a [i16]),
}

impl SlotData {
    fn zeroed(t: SampleType, n: usize) -> Self {
        match t {
            SampleType::U8 => SlotData::U8(vec![0; n]),
            SampleType::I8 => SlotData::I8(vec![0; n]),
            SampleType::U16 => SlotData::U16(vec![0; n]),
            SampleType::I16 => SlotData::I16(vec![0; n]),
            SampleType::F32 => SlotData::F32(vec![0.0; n]),
        }
    }

    fn len(&self) -> usize {
        self.borrow().len()
    }

    /// The borrowed form.
    pub fn borrow(&self) -> Samples<'_> {
        match self {
            SlotData::F32(d) => Samples::F32(d),
            SlotData::U8(d) => Samples::U8(d),
            SlotData::I8(d) => Samples::I8(d),
            SlotData::U16(d) => Samples::U16(d),
            SlotData::I16(d) => Samples::I16(d),
        }
    }

    fn write(&mut self, o: usize, samples: &[f32]) {
        fn put<T: Voxel>(d: &mut [T], src: &[f32]) {
            for (e, &v) in d.iter_mut().zip(src) {
                *e = T::from_value(v);
            }
        }
        let n = samples.len();
        match self {
            SlotData::F32(d) => d[o..o + n].copy_from_slice(samples),
            SlotData::U8(d) => put(&mut d[o..o + n], samples),
            SlotData::I8(d) => put(&mut d[o..o + n], samples),
            SlotData::U16(d) => put(&mut d[o..o + n], samples),
            SlotData::I16(d) => put(&mut d[o..o + n], samples),
        }
    }
}

impl<'a> Samples<'a> {
    /// Elements.
    pub fn len(&self) -> usize {
        match self {
            Samples::F32(d) => d.len(),
            Samples::U8(d) => d.len(),
            Samples::I8(d) => d.len(),
            Samples::U16(d) => d.len(),
            Samples::I16(d) => d.len(),
        }
    }

    /// Whether there are no elements (a bookkeeping-only pool).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Element `i` as its decoded value.
    #[inline]
    pub fn value(&self, i: usize) -> f32 {
        match self {
            Samples::F32(d) => d[i],
            Samples::U8(d) => d[i].value(),
            Samples::I8(d) => d[i].value(),
            Samples::U16(d) => d[i].value(),
            Samples::I16(d) => d[i].value(),
        }
    }

    /// Bytes per element.
    pub fn elem_bytes(&self) -> usize {
        match self {
            Samples::F32(_) => 4,
            Samples::U8(_) | Samples::I8(_) => 1,
            Samples::U16(_) | Samples::I16(_) => 2,
        }
    }
}

/// A pool of page slots.
#[derive(Debug)]
pub struct Pool {
    /// Samples per page (border included).
    pub page_samples: usize,
    /// `slots × page_samples` samples (empty for a bookkeeping-only pool).
    data: SlotData,
    /// Value ranges and visibility of the slots' macrocells (volume pools on the CPU).
    cells: Option<MacroCells>,
    /// Horizon pools: nodes per tile side, and per slot whether its tile is fragmented
    /// ([`strata_common::gpu::horizon_tile_fragmented`]).
    tiles: Option<(usize, Vec<bool>)>,
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
    /// A pool of f32 samples: `budget_bytes / page bytes` slots (at least one).
    pub fn new(page_samples: usize, budget_bytes: u64) -> Self {
        Self::typed(page_samples, budget_bytes, SampleType::F32)
    }

    /// A pool whose slots hold samples of type `t` (the decoded values must be integers of
    /// that type's range, or NaN-free for integer types): as many slots as `budget_bytes`
    /// holds at that width.
    pub fn typed(page_samples: usize, budget_bytes: u64, t: SampleType) -> Self {
        let n = Self::slots_of(page_samples, budget_bytes, t.size());
        let mut p = Self::bookkeeping(page_samples, n);
        // Padding past the last slot for the SIMD caster's 32-bit reads of 8-bit pairs.
        p.data = SlotData::zeroed(t, n * page_samples + crate::packet::POOL_PAD);
        p
    }

    /// Adds macrocells for pages of `page`³ samples (`page³ = page_samples`).
    pub fn with_cells(mut self, page: usize) -> Self {
        assert_eq!(
            page.pow(3),
            self.page_samples,
            "macrocells need cubic pages"
        );
        self.cells = Some(MacroCells::new(page, self.capacity()));
        self
    }

    /// Makes this a pool of horizon tiles of `side × side` nodes: each tile's fragmentation
    /// is computed as it enters its slot and shows in its page-table entry
    /// ([`ENTRY_FRAGMENTED`], through [`resident_of`](Self::resident_of)).
    pub fn with_tiles(mut self, side: usize) -> Self {
        assert_eq!(side * side, self.page_samples, "horizon tiles are square");
        self.tiles = Some((side, vec![false; self.capacity()]));
        self
    }

    /// Slots of `page_samples` f32 samples that fit `budget_bytes` (at least one).
    pub fn slots_for(page_samples: usize, budget_bytes: u64) -> usize {
        Self::slots_of(page_samples, budget_bytes, 4)
    }

    fn slots_of(page_samples: usize, budget_bytes: u64, elem: usize) -> usize {
        ((budget_bytes / (page_samples as u64 * elem as u64)) as usize).clamp(1, MAX_SLOTS)
    }

    /// A pool of `slots` slots whose samples live elsewhere (in a GPU buffer): only the
    /// slot records and the page → slot map are kept here.
    pub fn bookkeeping(page_samples: usize, slots: usize) -> Self {
        let n = slots.clamp(1, MAX_SLOTS);
        Pool {
            page_samples,
            data: SlotData::F32(Vec::new()),
            cells: None,
            tiles: None,
            slots: vec![SlotInfo::free(); n],
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

    /// How many pages [`place`](Self::place) can still take with `keep` protected: free
    /// slots and slots holding a page that is neither pinned nor kept.
    pub fn room(&self, keep: &HashSet<u64>) -> usize {
        self.free.len()
            + self
                .map
                .iter()
                .filter(|(k, &s)| self.slots[s as usize].pinned == 0 && !keep.contains(k))
                .count()
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
                    .filter(|(_, s)| s.pinned == 0 && !keep.contains(&s.page()))
                    // Among pages used as recently (every page of a round is touched in the
                    // same frame), the finest first: a coarse page is its children's
                    // fallback, and rounds place parents first, in lower slots, so by slot
                    // order they had gone first and left rays the root to fall back on.
                    .min_by_key(|(_, s)| (s.last_used, PageId(s.page()).level()))
                    .map(|(i, _)| i as u32)
                    .ok_or(PlaceError::Full)?;
                let old = self.slots[victim as usize].page();
                self.map.remove(&old);
                victim
            }
        };
        if self.data.len() > 0 {
            self.data.write(slot as usize * self.page_samples, samples);
            if let Some(c) = self.cells.as_mut() {
                c.compute(slot, |i| samples[i]);
            }
        }
        if let Some((side, f)) = self.tiles.as_mut() {
            f[slot as usize] = strata_common::gpu::horizon_tile_fragmented(samples, *side);
        }
        self.slots[slot as usize] = SlotInfo::new(key, frame, pinned);
        self.map.insert(key, slot);
        Ok(slot)
    }

    /// The samples of a slot of an f32 pool (horizon tiles are always f32).
    ///
    /// Panics on a pool of another type: callers that read volume slots go through
    /// [`samples`](Self::samples).
    #[inline(always)]
    pub fn slot_data(&self, slot: u32) -> &[f32] {
        let SlotData::F32(d) = &self.data else {
            panic!(
                "slot_data on a {:?}-element pool",
                self.samples().elem_bytes()
            );
        };
        let o = slot as usize * self.page_samples;
        &d[o..o + self.page_samples]
    }

    /// Every slot's samples (slot `s` starts at `s · page_samples`).
    #[inline(always)]
    pub fn samples(&self) -> Samples<'_> {
        self.data.borrow()
    }

    /// The macrocells, if the pool keeps them.
    pub fn cells(&self) -> Option<&MacroCells> {
        self.cells.as_ref()
    }

    /// Classifies the macrocells of `slot` (see [`MacroCells::classify`]); nothing without
    /// macrocells.
    pub fn classify(&mut self, slot: u32, visible: impl Fn(f32, f32) -> bool) {
        if let Some(c) = self.cells.as_mut() {
            c.classify(slot, visible);
        }
    }

    /// Bytes of sample storage per slot.
    pub fn slot_bytes(&self) -> usize {
        self.page_samples * self.samples().elem_bytes()
    }

    /// Resident pages of one data set, as a lookup for [`PageTable::rebuild`]: the slot,
    /// with [`ENTRY_FRAGMENTED`] for a fragmented horizon tile above level 0 (level 0 is
    /// drawn whatever its holes: there is nothing finer).
    pub fn resident_of(
        &self,
        dataset: u16,
        pyramid: &Pyramid,
    ) -> impl FnMut(usize, [u32; 3]) -> Option<u32> + '_ {
        let p = pyramid.clone();
        move |level, b| {
            let key = p.id(level, b).with_dataset(dataset).0;
            let slot = *self.map.get(&key)?;
            let fragmented =
                level > 0 && self.tiles.as_ref().is_some_and(|(_, f)| f[slot as usize]);
            Some(if fragmented {
                slot | ENTRY_FRAGMENTED
            } else {
                slot
            })
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

    /// A fragmented horizon tile's own entry carries the flag; the children that fall back
    /// on it do not (they are drawn with its data until their own arrive), and a slot
    /// reused for a whole tile loses it. Level 0 never carries it.
    #[test]
    fn only_a_fragmented_tiles_own_entry_carries_the_flag() {
        let p = Pyramid::new(Dim::Two, [40, 40, 1], 6, 1).unwrap(); // core 4
        let top = p.level_count() - 1;
        let mut pool = Pool::new(36, 36 * 4 * 4).with_tiles(6);
        let none = HashSet::new();
        let lines: Vec<f32> = (0..36)
            .map(|k| if k % 2 == 1 { f32::NAN } else { 1.0 })
            .collect();
        let whole = [1.0f32; 36];
        let (root, l1, l0) = (
            page_key(0, &p, top, [0, 0, 0]),
            page_key(0, &p, 1, [0, 0, 0]),
            page_key(0, &p, 0, [0, 0, 0]),
        );
        pool.place(root, &whole, 0, true, &none).unwrap();
        let s1 = pool.place(l1, &lines, 0, false, &none).unwrap();
        let s0 = pool.place(l0, &lines, 0, false, &none).unwrap();
        let mut t = PageTable::new(&p);
        t.rebuild(pool.resident_of(0, &p));
        assert_eq!(
            t.entries[t.index(1, [0, 0, 0])],
            s1 | 1 << 24 | ENTRY_FRAGMENTED
        );
        assert_eq!(t.entries[t.index(0, [1, 0, 0])], s1 | 1 << 24, "inherited");
        assert_eq!(t.entries[t.index(0, [0, 0, 0])], s0, "level 0 is drawn");
        assert_eq!(entry_level(t.entries[t.index(1, [0, 0, 0])]), 1);
        // The slot taken over by a whole tile.
        let mut pool2 = Pool::new(36, 36 * 4).with_tiles(6);
        pool2.place(l1, &lines, 0, false, &none).unwrap();
        let s = pool2.place(root, &whole, 1, true, &none).unwrap();
        assert_eq!(pool2.slot_of(l1), None);
        t.rebuild(pool2.resident_of(0, &p));
        assert_eq!(t.entries[t.index(top, [0, 0, 0])], s | (top as u32) << 24);
    }

    /// Pages touched in the same frame go finest first: a parent placed before its child
    /// (as rounds place them, so in a lower slot) outlives it.
    #[test]
    fn among_pages_used_as_recently_the_finest_is_evicted_first() {
        let p = Pyramid::new(Dim::Three, [128, 128, 128], 34, 1).unwrap(); // core 32
        let key = |l: usize, b: [u32; 3]| page_key(1, &p, l, b);
        let mut pool = Pool::new(8, 8 * 4 * 3);
        let none = HashSet::new();
        for (l, b) in [(2, [0, 0, 0]), (1, [0, 0, 0]), (0, [1, 0, 0])] {
            pool.place(key(l, b), &[1.0; 8], 5, false, &none).unwrap();
        }
        pool.place(key(0, [2, 0, 0]), &[2.0; 8], 6, false, &none)
            .unwrap();
        assert!(
            pool.slot_of(key(0, [1, 0, 0])).is_none(),
            "the level-0 page goes"
        );
        pool.place(key(0, [3, 0, 0]), &[3.0; 8], 6, false, &none)
            .unwrap();
        assert!(pool.slot_of(key(1, [0, 0, 0])).is_none(), "then level 1");
        assert!(pool.slot_of(key(2, [0, 0, 0])).is_some(), "the root stays");
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
