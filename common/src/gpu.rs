//! The tables both ray-casting backends read, as flat `#[repr(C)]` Pod records.
//!
//! The CPU caster walks these arrays in memory; the wgpu backend uploads the very same
//! bytes into storage buffers and its WGSL (`worker/src/gpu/cast.wgsl`) declares matching
//! structs. Nothing here holds a `u64` (WGSL has none without an extension), every record's
//! size and field offsets are fixed by the `const` assertions below, and a worker test
//! checks them against naga's layout of the shader's structs.
//!
//! * **Page table**: one `u32` per virtual page of every level of a data set, level 0
//!   first, bricks x fastest. An entry is `slot | level << 24` ([`page_entry`]): the slot of
//!   the page itself if resident, otherwise of its nearest resident ancestor and that
//!   ancestor's level. [`NOT_RESIDENT`] marks a page with no resident ancestor (never the
//!   case once a data set's root is pinned). A horizon tile's own entry may also carry
//!   [`ENTRY_FRAGMENTED`] (its level's cells are too broken up to draw it there).
//! * [`LevelInfo`]: where a level's entries start and its bricks per axis.
//! * [`SlotInfo`]: which page a pool slot holds, for eviction (host side only).
//! * [`FrameParams`], [`VolumeParams`], [`HorizonParams`]: one frame's camera, region,
//!   bands, volumes and horizons.
//! * Transfer-function tables: [`TF_SIZE`] premultiplied, step-corrected `[f32; 4]` entries
//!   per volume and band.

use crate::sample::SampleType;
use bytemuck::{Pod, Zeroable};
use std::mem::{offset_of, size_of};

/// Page-table entry for "nothing resident on the path to the root".
pub const NOT_RESIDENT: u32 = u32::MAX;
/// Bits of a page-table entry that hold the slot.
pub const SLOT_MASK: u32 = (1 << 24) - 1;
/// Bits of a page-table entry (after `>> 24`) that hold the level.
pub const LEVEL_MASK: u32 = 0x7f;
/// Flag of a horizon tile's own entry (set only where the tile itself is resident, never
/// inherited): the tile's level has lost most of its cells to holes (a coarse cell is a
/// hole wherever one of its fine nodes is, so regular lines of holes leave coarse tiles with
/// isolated nodes and no cell). Both casters then descend to its children instead of
/// drawing it ([`horizon_tile_fragmented`]). Volume entries never carry it.
pub const ENTRY_FRAGMENTED: u32 = 1 << 31;
/// Largest number of slots a pool may have.
pub const MAX_SLOTS: usize = SLOT_MASK as usize;
/// Entries of a transfer-function table.
pub const TF_SIZE: usize = 1024;
/// Sampling bands a frame may have (the step doubles per band).
pub const MAX_BANDS: usize = 8;
/// Levels a volume may have in the GPU tables (a 42-bit Morton code allows 15).
pub const MAX_LEVELS: usize = 16;

/// The page-table entry of a page resident in `slot` at `level`.
#[inline]
pub const fn page_entry(slot: u32, level: u32) -> u32 {
    slot | level << 24
}

/// The level an entry's slot holds (the entry's own page's, or its nearest resident
/// ancestor's), without the [`ENTRY_FRAGMENTED`] flag.
#[inline]
pub const fn entry_level(e: u32) -> u32 {
    (e >> 24) & LEVEL_MASK
}

/// Whether a horizon tile of `side × side` nodes (`NaN` = hole) is too broken up to be drawn
/// at its own level: the fraction of its cells that are whole (four valid nodes) is under
/// half the fraction of its nodes that are valid, or none of its nodes is. Coarsening makes a
/// node a hole wherever one of its children is, so a surface picked on every few lines has
/// coarse levels of isolated lines of nodes with no cell between them: those send the
/// casters to the finer levels, where the surface is whole. Scattered holes cost four cells
/// each and keep a tile at its level until they are about a fifth of its nodes: descending
/// costs four times the tiles per level, and a distant view of a surface riddled with holes
/// at every level would otherwise ask for its finest level.
pub fn horizon_tile_fragmented(nodes: &[f32], side: usize) -> bool {
    assert_eq!(nodes.len(), side * side, "a horizon tile of {side}² nodes");
    let valid = nodes.iter().filter(|h| !h.is_nan()).count();
    if valid == 0 || side < 2 {
        return true;
    }
    let mut cells = 0usize;
    for j in 0..side - 1 {
        let (a, b) = (
            &nodes[j * side..(j + 1) * side],
            &nodes[(j + 1) * side..(j + 2) * side],
        );
        for i in 0..side - 1 {
            if !(a[i].is_nan() || a[i + 1].is_nan() || b[i].is_nan() || b[i + 1].is_nan()) {
                cells += 1;
            }
        }
    }
    // cells / (side − 1)² < ½ · valid / side², in integers.
    2 * cells * side * side < valid * (side - 1) * (side - 1)
}

/// Per-level layout of a page table.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct LevelInfo {
    /// First entry of this level in the data set's table.
    pub offset: u32,
    /// Bricks per axis.
    pub bricks: [u32; 3],
}

/// One pool slot's record. The page key is split into two `u32` halves so the record stays
/// free of `u64`.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct SlotInfo {
    /// Low half of the page key held ([`SlotInfo::FREE`] in both halves when free).
    pub page_lo: u32,
    /// High half of the page key.
    pub page_hi: u32,
    /// Frame number of the last use.
    pub last_used: u32,
    /// 1 = pinned (a data set's root; never evicted).
    pub pinned: u32,
}

impl SlotInfo {
    /// The key half value of a free slot.
    pub const FREE: u32 = u32::MAX;

    /// The page key held, `u64::MAX` when free.
    #[inline]
    pub fn page(&self) -> u64 {
        (self.page_hi as u64) << 32 | self.page_lo as u64
    }

    /// A record for `page`.
    pub fn new(page: u64, last_used: u32, pinned: bool) -> Self {
        SlotInfo {
            page_lo: page as u32,
            page_hi: (page >> 32) as u32,
            last_used,
            pinned: pinned as u32,
        }
    }

    /// A free slot.
    pub fn free() -> Self {
        SlotInfo::new(u64::MAX, 0, false)
    }
}

/// One frame of one region: camera rays, the region box, sampling bands.
///
/// Positions are camera-relative (the eye at the origin) so f32 keeps its precision at UTM
/// coordinates. Ray `(x, y)` is `normalize(dir00 + (x + ½)·du + (y + ½)·dv)`.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct FrameParams {
    /// Ray direction through pixel corner (0, 0).
    pub dir00: [f32; 3],
    /// Image width.
    pub width: u32,
    /// Direction step per column.
    pub du: [f32; 3],
    /// Image height.
    pub height: u32,
    /// Direction step per row.
    pub dv: [f32; 3],
    /// Left column of the pixels that can see the region.
    pub rect_x: u32,
    /// Region box, lower corner.
    pub region_lo: [f32; 3],
    /// Top row of the rectangle.
    pub rect_y: u32,
    /// Region box, upper corner (half-open).
    pub region_hi: [f32; 3],
    /// Rectangle width.
    pub rect_w: u32,
    /// Start distance of each band (`band_start[0] = 0`).
    pub band_start: [f32; MAX_BANDS],
    /// Step of each band.
    pub band_dt: [f32; MAX_BANDS],
    /// Rectangle height.
    pub rect_h: u32,
    /// Bands in use.
    pub n_bands: u32,
    /// Volumes in use.
    pub n_vols: u32,
    /// Early ray termination threshold.
    pub ert: f32,
    /// [`FRAME_SHADING`]: read by the general pipeline, whose `SHADING` is compiled in
    /// whether the frame shades or not.
    pub flags: u32,
    /// Entries of the feedback buffer (the global page-table index space).
    pub fb_entries: u32,
    /// Horizons in use.
    pub n_hors: u32,
    /// Cross-worker occlusion: side in pixels of the blocks of the per-block ray
    /// thresholds buffer (`strata_common::occlusion::RayLimits`, one `f32` per block, < 0:
    /// not cast); 0: every ray of the rectangle with `ert`.
    pub occl_block: u32,
    /// A wall's tiles (`strata_common::wall::TileMap`): tile columns (1 for a plain image).
    /// Image pixel `(x, y)` lies on the plane of `dir00`, `du`, `dv` at
    /// `((t % tile_cols)·pitch_x + x, (t / tile_cols)·pitch_y + y − t·tile_h)`, `t = y / tile_h`.
    pub tile_cols: u32,
    /// Rows of the image per tile (the image height for a plain image).
    pub tile_h: u32,
    /// Plane pixels from one tile column to the next.
    pub pitch_x: u32,
    /// Plane pixels from one tile row to the next.
    pub pitch_y: u32,
}

/// One volume of a frame: its camera-relative → index transform, brick layout, LOD
/// distances, and where its page table and transfer-function tables start in the global
/// buffers.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct VolumeParams {
    /// Row 0 of the camera-relative → level-0 index linear map.
    pub m0: [f32; 3],
    /// Core samples per page axis.
    pub core: f32,
    /// Row 1.
    pub m1: [f32; 3],
    /// Border samples.
    pub border: f32,
    /// Row 2.
    pub m2: [f32; 3],
    /// Samples per page axis, border included.
    pub page: u32,
    /// Offset of the map.
    pub c: [f32; 3],
    /// Levels of the pyramid.
    pub n_levels: u32,
    /// Upper bound of the index box (`dims − ½`; the lower bound is −½).
    pub hi: [f32; 3],
    /// First entry of this data set's page table in the global table.
    pub table_base: u32,
    /// First [`LevelInfo`] of this data set in the global level array.
    pub level_base: u32,
    /// First entry of this volume's transfer-function tables (band `b` at `+ b·TF_SIZE`).
    pub tf_base: u32,
    /// Value → table position scale.
    pub tf_scale: f32,
    /// Value → table position offset.
    pub tf_offset: f32,
    /// Last table position (`TF_SIZE − 1`).
    pub tf_last: f32,
    /// First pool element of the pool this volume's pages live in (0: one pool).
    pub pool_base: u32,
    /// [`VOLUME_SIGNED`] | [`VOLUME_NO_DATA`] | [`VOLUME_INVISIBLE`].
    pub flags: u32,
    /// The integer pool value that means "no data" (with [`VOLUME_NO_DATA`]).
    pub no_data: i32,
    /// `level_t[l]`: distance from which level `l` is fine enough (`level_t[0] = 0`).
    pub level_t: [f32; MAX_LEVELS],
    /// Slices through the volume (at most [`MAX_SLICES`]).
    pub n_slices: u32,
    /// First entry of the straight-RGBA transfer-function table the slices are coloured
    /// by (in the transfer-function buffer).
    pub straight_base: u32,
    /// First slice record in the transfer-function buffer: one `[axis, level-0 index,
    /// opacity, 0]` per slice (the axis as a float 0, 1 or 2).
    pub slice_base: u32,
    /// With [`VOLUME_PREINTEGRATED`]: first entry of this volume's pre-integrated tables in
    /// the transfer-function buffer (`tf::PreintTable`). Entry `pre_base` is the value →
    /// table position map `[scale, offset, last, 0]`; band `b`'s whole-step table follows
    /// at `pre_base + 1 + 2·b·PREINT_SIZE²` and its half-step table `PREINT_SIZE²` entries
    /// later, each front value major.
    pub pre_base: u32,
}

/// Slices per volume, on either caster.
pub const MAX_SLICES: usize = 16;

/// [`VolumeParams::flags`]: the volume's samples are signed integers in an 8- or 16-bit pool.
pub const VOLUME_SIGNED: u32 = 1;
/// [`VolumeParams::flags`]: the pool value [`VolumeParams::no_data`] stands for no data (the
/// NaN of the decoded `f32` page).
pub const VOLUME_NO_DATA: u32 = 2;
/// [`VolumeParams::flags`]: the transfer function shows nothing of the volume (with
/// empty-space skipping): it is not marched, as on the CPU (its slices still show).
pub const VOLUME_INVISIBLE: u32 = 4;
/// [`VolumeParams::flags`]: the volume is pre-integrated (`render.preintegrated`): its
/// tables start at [`VolumeParams::pre_base`].
pub const VOLUME_PREINTEGRATED: u32 = 8;

/// How the device pool stores volume samples: in the narrowest width that holds every
/// volume's sample type (`u8`/`i8` → 8 bits, `u16`/`i16` → 16, `f32` → 32), so 8- and 16-bit
/// data are not widened to `f32` on the GPU. The shader decodes an element to the `f32` the
/// host's decoded page holds, bit for bit ([`PoolFormat::decode`] is its mirror).
///
/// A storage-buffer pool holds integers in two's complement. A texture pool (for the
/// texture unit's filter, `render.gpu_filter = "hardware"`) uses unsigned normalized texels,
/// so its signed values are *biased* by `2^(bits−1)`: filtering commutes with the bias and
/// the shader subtracts it after the filter.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct PoolFormat {
    /// Bits per element: 8, 16 or 32.
    pub bits: u32,
    /// Signed values are stored plus `2^(bits−1)` (unsigned-normalized texels).
    pub biased: bool,
}

impl PoolFormat {
    /// The format for volumes of these sample types (32 bits if there are none).
    pub fn for_types(types: impl IntoIterator<Item = SampleType>) -> Self {
        let bytes = types.into_iter().map(|t| t.size()).max().unwrap_or(4);
        PoolFormat {
            bits: 8 * bytes as u32,
            biased: false,
        }
    }

    /// What a signed volume's values are stored plus (0 for two's complement and for f32).
    pub fn bias(self, t: SampleType) -> i32 {
        if self.biased && self.bits < 32 && t.is_signed() {
            1 << (self.bits - 1)
        } else {
            0
        }
    }

    /// Elements per 32-bit word.
    pub fn per_word(self) -> usize {
        (32 / self.bits) as usize
    }

    /// Elements a slot of `page_samples` takes: whole 32-bit words, so every slot starts on a
    /// word (buffer writes are 4-byte aligned).
    pub fn slot_elems(self, page_samples: usize) -> usize {
        page_samples.next_multiple_of(self.per_word())
    }

    /// Bytes of a slot.
    pub fn slot_bytes(self, page_samples: usize) -> u64 {
        (self.slot_elems(page_samples) * (self.bits / 8) as usize) as u64
    }

    /// [`VolumeParams::flags`] and [`VolumeParams::no_data`] of a volume of type `t` with
    /// no-data sentinel `no_data`.
    pub fn volume_flags(self, t: SampleType, no_data: Option<f32>) -> (u32, i32) {
        if self.bits == 32 {
            return (0, 0); // f32 elements hold the NaN itself
        }
        let mut flags = 0;
        if t.is_signed() {
            flags |= VOLUME_SIGNED;
        }
        match no_data {
            Some(nd) => (flags | VOLUME_NO_DATA, nd as i32),
            None => (flags, 0),
        }
    }

    /// Appends the slot bytes of a decoded page (`f32`, NaN = no data; integer values of the
    /// volume's type `t`), zero-padded to [`slot_bytes`](Self::slot_bytes). NaN becomes the
    /// volume's sentinel (0 if it has none, as in the store encoder).
    pub fn encode(self, values: &[f32], t: SampleType, no_data: Option<f32>, out: &mut Vec<u8>) {
        let start = out.len();
        let nd = no_data.unwrap_or(0.0);
        let bias = self.bias(t);
        let int = |v: f32| if v.is_nan() { nd as i32 } else { v as i32 } + bias;
        match self.bits {
            8 => out.extend(values.iter().map(|&v| int(v) as u8)),
            16 => {
                for &v in values {
                    out.extend_from_slice(&(int(v) as u16).to_le_bytes());
                }
            }
            _ => {
                for &v in values {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        out.resize(start + self.slot_bytes(values.len()) as usize, 0);
    }

    /// Element `i` of a slot's bytes as the shader reads it, for a volume with these
    /// [`VolumeParams::flags`] and [`VolumeParams::no_data`].
    pub fn decode(self, bytes: &[u8], i: usize, flags: u32, no_data: i32) -> f32 {
        let signed = flags & VOLUME_SIGNED != 0;
        let raw = match self.bits {
            8 => {
                let b = bytes[i];
                match (signed, self.biased) {
                    (true, true) => b as i32 - 128,
                    (true, false) => b as i8 as i32,
                    _ => b as i32,
                }
            }
            16 => {
                let h = u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]]);
                match (signed, self.biased) {
                    (true, true) => h as i32 - 32768,
                    (true, false) => h as i16 as i32,
                    _ => h as i32,
                }
            }
            _ => {
                let w = &bytes[4 * i..4 * i + 4];
                return f32::from_le_bytes([w[0], w[1], w[2], w[3]]);
            }
        };
        if flags & VOLUME_NO_DATA != 0 && raw == no_data {
            return f32::NAN;
        }
        raw as f32
    }
}

/// [`HorizonParams::flags`]: colour by height through the colour map.
pub const HORIZON_DEPTH_MAP: u32 = 1;
/// [`FrameParams::flags`]: gradient shading of volumes.
pub const FRAME_SHADING: u32 = 1;
/// [`HorizonParams::flags`]: Lambert (headlight) shading.
pub const HORIZON_LIGHTING: u32 = 2;
/// [`HorizonParams::attr_vol`] of a horizon not coloured by a volume.
pub const NO_VOLUME: u32 = u32::MAX;
/// Horizons the GPU caster intersects at most.
pub const MAX_HORIZONS: usize = 16;

/// One horizon of a frame: its camera-relative → index (i, j, height) transform, tile
/// layout, LOD distances, colouring, and where its page table, tile bounds and colour map
/// start in the global buffers.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct HorizonParams {
    /// Row 0 of the camera-relative → level-0 index linear map.
    pub m0: [f32; 3],
    /// Core nodes per tile axis.
    pub core: u32,
    /// Row 1.
    pub m1: [f32; 3],
    /// Border nodes.
    pub border: u32,
    /// Row 2 (the height row).
    pub m2: [f32; 3],
    /// Nodes per tile axis, border included.
    pub page: u32,
    /// Offset of the map.
    pub c: [f32; 3],
    /// Levels of the tile tree.
    pub n_levels: u32,
    /// Straight linear RGB for a constant colour.
    pub color: [f32; 3],
    /// Opacity.
    pub opacity: f32,
    /// Level-0 nodes per axis (i, j).
    pub dims: [u32; 2],
    /// First entry of this data set's page table in the global table.
    pub table_base: u32,
    /// First [`LevelInfo`] of this data set in the global level array.
    pub level_base: u32,
    /// First `[min, max]` of this horizon in the global tile-bounds array (page-table order;
    /// an all-hole tile has `min > max`).
    pub bounds_base: u32,
    /// First colour-map point in the colour buffer.
    pub map_base: u32,
    /// Colour-map points (at least 2 with [`HORIZON_DEPTH_MAP`]).
    pub map_len: u32,
    /// [`HORIZON_DEPTH_MAP`] | [`HORIZON_LIGHTING`].
    pub flags: u32,
    /// Height at the colour map's start.
    pub depth_lo: f32,
    /// Height at its end.
    pub depth_hi: f32,
    /// First sample of the horizon pool (0: one pool for all horizons).
    pub pool_base: u32,
    /// `color_by = "volume"`: the volume whose straight transfer-function colour multiplies
    /// each hit (`color` is then white and `tf[map_base]` holds the no-data colour);
    /// [`NO_VOLUME`] otherwise.
    pub attr_vol: u32,
    /// `level_t[l]`: distance from which level `l` is fine enough (`level_t[0] = 0`).
    pub level_t: [f32; MAX_LEVELS],
}

// The WGSL structs mirror these byte for byte (vec3<f32> is 16-aligned, hence the scalar
// after every [f32; 3]); the worker's naga test compares them with the shader.
const _: () = assert!(size_of::<LevelInfo>() == 16);
const _: () = assert!(size_of::<SlotInfo>() == 16);
const _: () = assert!(size_of::<FrameParams>() == 192);
const _: () = assert!(offset_of!(FrameParams, band_start) == 80);
const _: () = assert!(offset_of!(FrameParams, band_dt) == 112);
const _: () = assert!(offset_of!(FrameParams, rect_h) == 144);
const _: () = assert!(offset_of!(FrameParams, flags) == 160);
const _: () = assert!(size_of::<VolumeParams>() == 192);
const _: () = assert!(offset_of!(VolumeParams, n_slices) == 176);
const _: () = assert!(offset_of!(VolumeParams, slice_base) == 184);
const _: () = assert!(offset_of!(VolumeParams, pre_base) == 188);
const _: () = assert!(offset_of!(VolumeParams, table_base) == 76);
const _: () = assert!(offset_of!(VolumeParams, level_base) == 80);
const _: () = assert!(offset_of!(VolumeParams, level_t) == 112);
const _: () = assert!(size_of::<VolumeParams>().is_multiple_of(16));
const _: () = assert!(offset_of!(FrameParams, n_hors) == 168);
const _: () = assert!(size_of::<HorizonParams>() == 192);
const _: () = assert!(offset_of!(HorizonParams, dims) == 80);
const _: () = assert!(offset_of!(HorizonParams, depth_lo) == 112);
const _: () = assert!(offset_of!(HorizonParams, level_t) == 128);

/// Field offsets of [`FrameParams`] by WGSL member name, for the layout check.
pub fn frame_params_offsets() -> Vec<(&'static str, usize)> {
    vec![
        ("dir00", offset_of!(FrameParams, dir00)),
        ("width", offset_of!(FrameParams, width)),
        ("du", offset_of!(FrameParams, du)),
        ("height", offset_of!(FrameParams, height)),
        ("dv", offset_of!(FrameParams, dv)),
        ("rect_x", offset_of!(FrameParams, rect_x)),
        ("region_lo", offset_of!(FrameParams, region_lo)),
        ("rect_y", offset_of!(FrameParams, rect_y)),
        ("region_hi", offset_of!(FrameParams, region_hi)),
        ("rect_w", offset_of!(FrameParams, rect_w)),
        ("band_start", offset_of!(FrameParams, band_start)),
        ("band_dt", offset_of!(FrameParams, band_dt)),
        ("rect_h", offset_of!(FrameParams, rect_h)),
        ("n_bands", offset_of!(FrameParams, n_bands)),
        ("n_vols", offset_of!(FrameParams, n_vols)),
        ("ert", offset_of!(FrameParams, ert)),
        ("flags", offset_of!(FrameParams, flags)),
        ("fb_entries", offset_of!(FrameParams, fb_entries)),
        ("n_hors", offset_of!(FrameParams, n_hors)),
        ("occl_block", offset_of!(FrameParams, occl_block)),
        ("tile_cols", offset_of!(FrameParams, tile_cols)),
        ("tile_h", offset_of!(FrameParams, tile_h)),
        ("pitch_x", offset_of!(FrameParams, pitch_x)),
        ("pitch_y", offset_of!(FrameParams, pitch_y)),
    ]
}

/// Field offsets of [`VolumeParams`] by WGSL member name, for the layout check.
pub fn volume_params_offsets() -> Vec<(&'static str, usize)> {
    vec![
        ("m0", offset_of!(VolumeParams, m0)),
        ("core", offset_of!(VolumeParams, core)),
        ("m1", offset_of!(VolumeParams, m1)),
        ("border", offset_of!(VolumeParams, border)),
        ("m2", offset_of!(VolumeParams, m2)),
        ("page", offset_of!(VolumeParams, page)),
        ("c", offset_of!(VolumeParams, c)),
        ("n_levels", offset_of!(VolumeParams, n_levels)),
        ("hi", offset_of!(VolumeParams, hi)),
        ("table_base", offset_of!(VolumeParams, table_base)),
        ("level_base", offset_of!(VolumeParams, level_base)),
        ("tf_base", offset_of!(VolumeParams, tf_base)),
        ("tf_scale", offset_of!(VolumeParams, tf_scale)),
        ("tf_offset", offset_of!(VolumeParams, tf_offset)),
        ("tf_last", offset_of!(VolumeParams, tf_last)),
        ("pool_base", offset_of!(VolumeParams, pool_base)),
        ("flags", offset_of!(VolumeParams, flags)),
        ("no_data", offset_of!(VolumeParams, no_data)),
        ("level_t", offset_of!(VolumeParams, level_t)),
        ("n_slices", offset_of!(VolumeParams, n_slices)),
        ("straight_base", offset_of!(VolumeParams, straight_base)),
        ("slice_base", offset_of!(VolumeParams, slice_base)),
        ("pre_base", offset_of!(VolumeParams, pre_base)),
    ]
}

/// Field offsets of [`HorizonParams`] by WGSL member name, for the layout check.
pub fn horizon_params_offsets() -> Vec<(&'static str, usize)> {
    vec![
        ("m0", offset_of!(HorizonParams, m0)),
        ("core", offset_of!(HorizonParams, core)),
        ("m1", offset_of!(HorizonParams, m1)),
        ("border", offset_of!(HorizonParams, border)),
        ("m2", offset_of!(HorizonParams, m2)),
        ("page", offset_of!(HorizonParams, page)),
        ("c", offset_of!(HorizonParams, c)),
        ("n_levels", offset_of!(HorizonParams, n_levels)),
        ("color", offset_of!(HorizonParams, color)),
        ("opacity", offset_of!(HorizonParams, opacity)),
        ("dims", offset_of!(HorizonParams, dims)),
        ("table_base", offset_of!(HorizonParams, table_base)),
        ("level_base", offset_of!(HorizonParams, level_base)),
        ("bounds_base", offset_of!(HorizonParams, bounds_base)),
        ("map_base", offset_of!(HorizonParams, map_base)),
        ("map_len", offset_of!(HorizonParams, map_len)),
        ("flags", offset_of!(HorizonParams, flags)),
        ("depth_lo", offset_of!(HorizonParams, depth_lo)),
        ("depth_hi", offset_of!(HorizonParams, depth_hi)),
        ("pool_base", offset_of!(HorizonParams, pool_base)),
        ("attr_vol", offset_of!(HorizonParams, attr_vol)),
        ("level_t", offset_of!(HorizonParams, level_t)),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slot_info_splits_the_key_without_loss() {
        for k in [
            0u64,
            1,
            0xdead_beef_1234_5678,
            u64::MAX,
            1 << 32,
            (1 << 32) - 1,
        ] {
            assert_eq!(SlotInfo::new(k, 3, true).page(), k);
        }
        assert_eq!(SlotInfo::free().page(), u64::MAX);
        assert_eq!(page_entry(5, 3) & SLOT_MASK, 5);
        assert_eq!(page_entry(5, 3) >> 24, 3);
        assert_eq!(entry_level(page_entry(5, 3) | ENTRY_FRAGMENTED), 3);
        assert_eq!(
            (page_entry(5, 3) | ENTRY_FRAGMENTED) & SLOT_MASK,
            5,
            "the flag leaves the slot alone"
        );
        // The largest level and slot with the flag is still not NOT_RESIDENT.
        let top = page_entry(SLOT_MASK - 1, MAX_LEVELS as u32 - 1) | ENTRY_FRAGMENTED;
        assert_ne!(top, NOT_RESIDENT);
    }

    /// Whole tiles, scattered holes and lines of holes three or more apart are drawn at
    /// their level; isolated lines or points of nodes (no cell), and all-hole tiles, are not.
    #[test]
    fn horizon_tiles_are_fragmented_by_lines_of_holes_not_by_isolated_ones() {
        let side = 18;
        let tile = |hole: &dyn Fn(usize, usize) -> bool| -> Vec<f32> {
            (0..side * side)
                .map(|k| {
                    if hole(k % side, k / side) {
                        f32::NAN
                    } else {
                        1.0
                    }
                })
                .collect()
        };
        assert!(!horizon_tile_fragmented(&tile(&|_, _| false), side));
        // One in four (every other node of every other row): no cell left; one in nine
        // (4 cells in 9 lost) stays.
        assert!(horizon_tile_fragmented(
            &tile(&|i, j| i % 2 == 1 && j % 2 == 1),
            side
        ));
        assert!(!horizon_tile_fragmented(
            &tile(&|i, j| i % 3 == 1 && j % 3 == 1),
            side
        ));
        // One hole in 36 nodes: 4 cells in 36 lost.
        assert!(!horizon_tile_fragmented(
            &tile(&|i, j| i % 6 == 2 && j % 6 == 3),
            side
        ));
        // A tile half beyond the grid's edge.
        assert!(!horizon_tile_fragmented(&tile(&|i, _| i >= 9), side));
        // Every other column, every third: isolated lines of nodes, no cell.
        assert!(horizon_tile_fragmented(&tile(&|i, _| i % 2 == 1), side));
        assert!(horizon_tile_fragmented(&tile(&|i, _| i % 3 != 0), side));
        // Lines of holes every third column (2 of 3 columns valid, 1 of 3 cells whole: half
        // the node fraction) and every fourth (⅔ of it) stay.
        assert!(!horizon_tile_fragmented(&tile(&|i, _| i % 3 == 2), side));
        assert!(!horizon_tile_fragmented(&tile(&|i, _| i % 4 == 3), side));
        // One line of nodes along the edge (a tile just past the grid's last column).
        assert!(horizon_tile_fragmented(&tile(&|i, _| i != 0), side));
        assert!(horizon_tile_fragmented(&tile(&|_, _| true), side));
    }

    /// Every sample type's decoded values survive the pool encoding bit for bit, in every
    /// pool width that holds the type, sentinels included.
    #[test]
    fn pool_elements_decode_to_the_hosts_f32() {
        use SampleType::*;
        let cases: [(SampleType, Option<f32>, Vec<f32>); 5] = [
            (U8, None, vec![0.0, 1.0, 127.0, 128.0, 255.0]),
            (
                I8,
                Some(-128.0),
                vec![-127.0, -1.0, 0.0, 5.0, 127.0, f32::NAN],
            ),
            (
                U16,
                Some(65535.0),
                vec![0.0, 300.0, 40000.0, 65534.0, f32::NAN],
            ),
            (
                I16,
                Some(-32768.0),
                vec![-32767.0, -2.0, 0.0, 12345.0, 32767.0, f32::NAN],
            ),
            (F32, None, vec![-1.5e-7, 0.0, 3.25, 1e30, f32::NAN]),
        ];
        for (t, nd, values) in cases {
            for (bits, biased) in [8u32, 16, 32]
                .into_iter()
                .flat_map(|b| [(b, false), (b, true)])
            {
                if bits < 8 * t.size() as u32 {
                    continue;
                }
                let f = PoolFormat { bits, biased };
                let (flags, ndi) = f.volume_flags(t, nd);
                let mut bytes = vec![0xAB]; // encoding appends
                f.encode(&values, t, nd, &mut bytes);
                let slot = &bytes[1..];
                assert_eq!(slot.len() as u64, f.slot_bytes(values.len()));
                assert_eq!(slot.len() % 4, 0);
                for (i, &v) in values.iter().enumerate() {
                    let got = f.decode(slot, i, flags, ndi);
                    assert!(
                        got.to_bits() == v.to_bits() || (got.is_nan() && v.is_nan()),
                        "{t:?} in {bits}-bit pool: {v} became {got}"
                    );
                }
            }
        }
        assert_eq!(PoolFormat::for_types([U8, I8]).bits, 8);
        assert_eq!(PoolFormat::for_types([U8, I16]).bits, 16);
        assert_eq!(PoolFormat::for_types([U16, F32]).bits, 32);
        let f8 = PoolFormat {
            bits: 8,
            biased: false,
        };
        assert_eq!(f8.slot_elems(4913), 4916);
        // Biased signed texels are ordered as the values are (filtering commutes with it).
        let b8 = PoolFormat { biased: true, ..f8 };
        let mut bytes = Vec::new();
        b8.encode(&[-128.0, -1.0, 0.0, 127.0], I8, None, &mut bytes);
        assert_eq!(bytes, [0, 127, 128, 255]);
    }
}
