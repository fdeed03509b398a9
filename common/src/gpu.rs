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
//!   case once a data set's root is pinned).
//! * [`LevelInfo`]: where a level's entries start and its bricks per axis.
//! * [`SlotInfo`]: which page a pool slot holds, for eviction (host side only).
//! * [`FrameParams`], [`VolumeParams`], [`HorizonParams`]: one frame's camera, region,
//!   bands, volumes and horizons.
//! * Transfer-function tables: [`TF_SIZE`] premultiplied, step-corrected `[f32; 4]` entries
//!   per volume and band.

use bytemuck::{Pod, Zeroable};
use std::mem::{offset_of, size_of};

/// Page-table entry for "nothing resident on the path to the root".
pub const NOT_RESIDENT: u32 = u32::MAX;
/// Bits of a page-table entry that hold the slot.
pub const SLOT_MASK: u32 = (1 << 24) - 1;
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
    /// Reserved (0).
    pub flags: u32,
    /// Entries of the feedback buffer (the global page-table index space).
    pub fb_entries: u32,
    /// Horizons in use.
    pub n_hors: u32,
    /// Padding.
    pub _pad: u32,
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
    /// First slot sample of the pool this volume's pages live in (0: one pool per type).
    pub pool_base: u32,
    /// Padding.
    pub _pad: [u32; 2],
    /// `level_t[l]`: distance from which level `l` is fine enough (`level_t[0] = 0`).
    pub level_t: [f32; MAX_LEVELS],
}

/// [`HorizonParams::flags`]: colour by height through the colour map.
pub const HORIZON_DEPTH_MAP: u32 = 1;
/// [`HorizonParams::flags`]: Lambert (headlight) shading.
pub const HORIZON_LIGHTING: u32 = 2;
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
    /// Padding.
    pub _pad: u32,
    /// `level_t[l]`: distance from which level `l` is fine enough (`level_t[0] = 0`).
    pub level_t: [f32; MAX_LEVELS],
}

// The WGSL structs mirror these byte for byte (vec3<f32> is 16-aligned, hence the scalar
// after every [f32; 3]); the worker's naga test compares them with the shader.
const _: () = assert!(size_of::<LevelInfo>() == 16);
const _: () = assert!(size_of::<SlotInfo>() == 16);
const _: () = assert!(size_of::<FrameParams>() == 176);
const _: () = assert!(offset_of!(FrameParams, band_start) == 80);
const _: () = assert!(offset_of!(FrameParams, band_dt) == 112);
const _: () = assert!(offset_of!(FrameParams, rect_h) == 144);
const _: () = assert!(offset_of!(FrameParams, flags) == 160);
const _: () = assert!(size_of::<VolumeParams>() == 176);
const _: () = assert!(offset_of!(VolumeParams, table_base) == 76);
const _: () = assert!(offset_of!(VolumeParams, level_base) == 80);
const _: () = assert!(offset_of!(VolumeParams, level_t) == 112);
const _: () = assert!(size_of::<VolumeParams>() % 16 == 0);
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
        ("level_t", offset_of!(VolumeParams, level_t)),
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
    }
}
