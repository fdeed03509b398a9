//! The engine's side of the GPU backend: lays the page tables of every data set (volumes,
//! then horizons) out in one global index space, turns a [`FrameSetup`] into the shared
//! `strata_common::gpu` records, and turns the compacted feedback back into page keys.

use super::{AdapterChoice, GpuCaster, MAX_VOLUMES};
use crate::atlas::PageTable;
use crate::feedback::Feedback;
use crate::raycast::{CastStats, FrameSetup};
use anyhow::{bail, Result};
use strata_common::gpu::{
    FrameParams, HorizonParams, PoolFormat, VolumeParams, HORIZON_DEPTH_MAP, HORIZON_LIGHTING,
    MAX_BANDS, MAX_HORIZONS, MAX_LEVELS, MAX_SLICES, NO_VOLUME, TF_SIZE,
};
use strata_common::image::PartialImage;
use strata_common::pyramid::Pyramid;
use strata_common::sample::SampleType;
use strata_common::scene::GpuFilter;

/// The GPU caster plus where each data set's page table lives in the global tables.
pub struct GpuBackend {
    caster: GpuCaster,
    /// Volumes (data sets `0..volumes`; horizons follow).
    volumes: usize,
    /// First global entry of each data set's table.
    table_base: Vec<u32>,
    /// First global level record of each data set.
    level_base: Vec<u32>,
    /// Global entries in all.
    entries: u32,
    pyramids: Vec<Pyramid>,
    global: Vec<u32>,
    /// How the volume pool stores samples.
    format: PoolFormat,
    /// Shader trilinear over a buffer pool, or the texture unit over a texture pool.
    filter: GpuFilter,
    /// Each volume's sample type and no-data sentinel.
    types: Vec<(SampleType, Option<f32>)>,
    scratch: Vec<u8>,
    /// The pre-integration tables as last laid out for the shader.
    pre: PreRegion,
}

/// The pre-integration tables of a frame's volumes, laid out once at the start of the
/// transfer-function buffer and kept while the engine hands out the same tables: they are
/// 2 MiB per band, and the engine's cache returns the same `Arc`s until the transfer
/// function or the bands change.
#[derive(Default)]
struct PreRegion {
    /// Per volume, the tables laid out (empty: not pre-integrated).
    key: Vec<Vec<std::sync::Arc<strata_common::tf::PreintTable>>>,
    /// Per volume, its first record (`VolumeParams::pre_base`).
    base: Vec<u32>,
    /// The records.
    data: Vec<[f32; 4]>,
    /// Bumped whenever `data` changes.
    generation: u64,
}

impl PreRegion {
    /// Lays out the volumes' tables unless they are the ones laid out already.
    fn update<'v>(
        &mut self,
        pres: impl ExactSizeIterator<
            Item = Option<&'v [std::sync::Arc<strata_common::tf::PreintTable>]>,
        >,
    ) -> Result<()> {
        let pres: Vec<&[std::sync::Arc<strata_common::tf::PreintTable>]> =
            pres.map(|p| p.unwrap_or(&[])).collect();
        let same = self.key.len() == pres.len()
            && self.key.iter().zip(&pres).all(|(k, p)| {
                k.len() == p.len()
                    && k.iter()
                        .zip(p.iter())
                        .all(|(a, b)| std::sync::Arc::ptr_eq(a, b))
            });
        if same {
            return Ok(());
        }
        let n = strata_common::tf::PREINT_SIZE;
        // A new generation whatever follows: the data changes from here.
        self.generation += 1;
        self.data.clear();
        self.base.clear();
        self.key.clear();
        for pre in &pres {
            self.base.push(self.data.len() as u32);
            self.key.push(pre.to_vec());
            let Some(p0) = pre.first() else { continue };
            // The position map, then per band the whole- and half-step tables.
            self.data.push([p0.scale, p0.offset, p0.last, 0.0]);
            for p in pre.iter() {
                if p.entries.len() != n * n || p.half_entries.len() != n * n {
                    self.key.clear(); // nothing valid laid out
                    bail!(
                        "a pre-integrated table of {} entries, not {}",
                        p.entries.len(),
                        n * n
                    );
                }
                self.data.extend_from_slice(&p.entries);
                self.data.extend_from_slice(&p.half_entries);
            }
        }
        Ok(())
    }
}

/// What a GPU frame adds to the CPU's counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct GpuFrameStats {
    /// Bytes read back (pixels, feedback, counters).
    pub readback_bytes: u64,
    /// Feedback bytes read back (length and compact list).
    pub feedback_bytes: u64,
    /// Bytes written to the device since the previous frame (pages, tables).
    pub uploaded_bytes: u64,
}

/// LOD distances padded to the shader's fixed array (levels are checked at open).
fn level_t_array(t: &[f32]) -> [f32; MAX_LEVELS] {
    let mut a = [0f32; MAX_LEVELS];
    a[..t.len()].copy_from_slice(t);
    a
}

/// A page table's level records as the shader reads them: first entry, bricks per axis.
fn level_records(t: &PageTable) -> impl Iterator<Item = [u32; 4]> + '_ {
    t.levels
        .iter()
        .map(|l| [l.offset, l.bricks[0], l.bricks[1], l.bricks[2]])
}

impl GpuBackend {
    /// Opens the adapter for data sets with these pyramids, in data-set order: the volumes
    /// (with their sample types and no-data sentinels in `types`), then horizons.
    pub fn new(
        choice: &AdapterChoice,
        pyramids: Vec<Pyramid>,
        types: Vec<(SampleType, Option<f32>)>,
        filter: GpuFilter,
    ) -> Result<Self> {
        let volumes = types.len();
        let horizons = pyramids.len().saturating_sub(volumes);
        if pyramids.is_empty() || volumes > MAX_VOLUMES || horizons > MAX_HORIZONS {
            bail!(
                "the GPU caster renders up to {MAX_VOLUMES} volumes and {MAX_HORIZONS} horizons, \
                 the scene has {volumes} and {horizons}"
            );
        }
        for p in &pyramids {
            if p.level_count() > MAX_LEVELS {
                bail!(
                    "a volume of {} levels exceeds the GPU caster's {MAX_LEVELS}",
                    p.level_count()
                );
            }
        }
        let caster = GpuCaster::new(choice)?;
        let mut table_base = Vec::new();
        let mut level_base = Vec::new();
        let (mut n, mut nl) = (0u64, 0u32);
        for p in &pyramids {
            table_base.push(n as u32);
            level_base.push(nl);
            let t = PageTable::new(p);
            n += t.entries.len() as u64;
            nl += t.levels.len() as u32;
        }
        tables_fit(n, caster.max_binding_bytes())?;
        let mut format = PoolFormat::for_types(types.iter().map(|t| t.0));
        if filter == GpuFilter::Hardware {
            // Unsigned-normalized texels, signed values biased; a 16-bit pool the adapter
            // cannot filter widens to f32 texels (which must then be filterable).
            format.biased = true;
            if !caster.can_filter(format.bits) {
                format.bits = 32;
            }
            if !caster.can_filter(format.bits) {
                bail!(
                    "render.gpu_filter = \"hardware\": adapter {} cannot filter this pool's \
                     textures; use \"exact\"",
                    caster.adapter_name()
                );
            }
        }
        Ok(GpuBackend {
            filter,
            format,
            types,
            scratch: Vec::new(),
            pre: PreRegion::default(),
            caster,
            volumes,
            table_base,
            level_base,
            entries: n as u32,
            pyramids,
            global: Vec::new(),
        })
    }

    /// The adapter's name and API.
    pub fn adapter_name(&self) -> String {
        self.caster.adapter_name()
    }

    /// The volume pool's element format.
    pub fn pool_format(&self) -> PoolFormat {
        self.format
    }

    /// The most pixels one band of a cast may have ([`GpuCaster::max_frame_pixels`]).
    pub fn max_frame_pixels(&self) -> u64 {
        self.caster.max_frame_pixels()
    }

    /// Caps a band's pixels ([`GpuCaster::set_band_pixels`]).
    pub fn set_band_pixels(&mut self, cap: Option<u64>) {
        self.caster.set_band_pixels(cap);
    }

    /// Test hook: [`GpuCaster::fail_an_allocation`].
    #[doc(hidden)]
    pub fn fail_an_allocation(&mut self) -> bool {
        self.caster.fail_an_allocation()
    }

    /// Test hook: [`GpuCaster::write_past_a_buffer`].
    #[doc(hidden)]
    pub fn write_past_a_buffer(&mut self) {
        self.caster.write_past_a_buffer();
    }

    /// Bytes of the image buffer ([`GpuCaster::image_buffer_bytes`]).
    #[doc(hidden)]
    pub fn image_buffer_bytes(&self) -> u64 {
        self.caster.image_buffer_bytes()
    }

    /// Regions cast in more than one band ([`GpuCaster::banded_regions`]).
    pub fn banded_regions(&self) -> u64 {
        self.caster.banded_regions()
    }

    /// Volume-pool slots for pages of `page_samples` samples: as many as `budget_bytes` holds
    /// in the pool's format and the adapter can bind (at least one).
    pub fn volume_slots(&self, page_samples: usize, budget_bytes: u64) -> (usize, usize) {
        let slot = self.format.slot_bytes(page_samples);
        let want = ((budget_bytes / slot) as usize).clamp(1, strata_common::gpu::MAX_SLOTS);
        let fit = match self.filter {
            GpuFilter::Exact => self.caster.max_slots(slot),
            GpuFilter::Hardware => self
                .caster
                .max_texture_slots(self.volume_page(), self.format.bits / 8),
        };
        (want, want.min(fit))
    }

    /// Samples per volume-page axis.
    fn volume_page(&self) -> u32 {
        self.pyramids.first().map_or(1, |p| p.page())
    }

    /// The volume filter in use.
    pub fn filter(&self) -> GpuFilter {
        self.filter
    }

    /// Horizon-pool slots (f32 heights) the adapter can bind.
    pub fn max_horizon_slots(&self, page_samples: usize) -> usize {
        self.caster.max_slots(page_samples as u64 * 4)
    }

    /// Allocates the device's volume pool.
    pub fn alloc_pool(&mut self, slots: usize, page_samples: usize) -> Result<()> {
        match self.filter {
            GpuFilter::Exact => self.caster.alloc_pool(
                slots,
                self.format.slot_bytes(page_samples),
                self.format.bits,
            ),
            GpuFilter::Hardware => {
                self.caster
                    .alloc_texture_pool(slots, self.volume_page(), self.format.bits)
            }
        }
    }

    /// Allocates the device's horizon pool.
    pub fn alloc_horizon_pool(&mut self, slots: usize, page_samples: usize) -> Result<()> {
        self.caster.alloc_horizon_pool(slots, page_samples)
    }

    /// Writes a newly resident page of data set `ds` into its slot (of the volume or the
    /// horizon pool).
    pub fn write_page(&mut self, ds: u16, slot: u32, samples: &[f32]) {
        if let Some(&(t, no_data)) = self.types.get(ds as usize) {
            self.scratch.clear();
            self.format.encode(samples, t, no_data, &mut self.scratch);
            self.caster.write_page(slot, &self.scratch);
        } else {
            self.caster.write_horizon_page(slot, samples);
        }
    }

    /// Writes the changed entries of the data sets' page tables; returns how many.
    pub fn sync_tables(&mut self, tables: &[PageTable]) -> usize {
        self.global.clear();
        for t in tables.iter().take(self.pyramids.len()) {
            self.global.extend_from_slice(&t.entries);
        }
        debug_assert_eq!(self.global.len(), self.entries as usize);
        self.caster.sync_table(&self.global)
    }

    /// Bytes written to the device since the last cast (or the last call): pages and
    /// tables of the updates after it.
    pub fn take_uploaded(&mut self) -> u64 {
        self.caster.take_uploaded()
    }

    /// Casts the frame on the GPU: the same image, feedback and counters as
    /// [`FrameSetup::render`] gives on the CPU.
    pub fn render(
        &mut self,
        setup: &FrameSetup<'_>,
    ) -> Result<(PartialImage, Feedback, CastStats, GpuFrameStats)> {
        let r = setup.rect;
        let mut stats = GpuFrameStats::default();
        if r.w == 0 || r.h == 0 {
            stats.uploaded_bytes = self.caster.take_uploaded();
            let image = PartialImage {
                width: setup.width,
                height: setup.height,
                rect: r,
                pixels: Vec::new(),
            };
            return Ok((image, Feedback::default(), CastStats::default(), stats));
        }
        let nb = setup.bands.dt.len();
        if nb > MAX_BANDS {
            bail!("{nb} sampling bands exceed the GPU caster's {MAX_BANDS}");
        }
        let mut band_start = [0f32; MAX_BANDS];
        let mut band_dt = [0f32; MAX_BANDS];
        band_start[..nb].copy_from_slice(&setup.bands.start);
        band_dt[..nb].copy_from_slice(&setup.bands.dt);
        let frame = FrameParams {
            dir00: setup.dir00,
            width: setup.width,
            du: setup.du,
            height: setup.height,
            dv: setup.dv,
            rect_x: r.x,
            region_lo: setup.region_lo,
            rect_y: r.y,
            region_hi: setup.region_hi,
            rect_w: r.w,
            band_start,
            band_dt,
            rect_h: r.h,
            n_bands: nb as u32,
            n_vols: setup.vols.len() as u32,
            ert: setup.ert,
            // Shading where a volume is marched (the frame's effects): an invisible volume
            // is not, and its slices are not shaded.
            flags: if setup
                .variant
                .effects
                .contains(strata_common::effects::EffectSet::SHADING)
            {
                strata_common::gpu::FRAME_SHADING
            } else {
                0
            },
            fb_entries: self.entries,
            n_hors: setup.hors.len() as u32,
            occl_block: setup.limits.map_or(0, |l| l.front.grid.block),
            tile_cols: setup.tiles.cols,
            tile_h: setup.tiles.tile_h,
            pitch_x: setup.tiles.pitch_x,
            pitch_y: setup.tiles.pitch_y,
        };
        // Per block: the ray threshold the CPU caster would use, < 0 for rays not cast.
        let occl: Option<Vec<f32>> = setup.limits.map(|l| {
            (0..l.front.grid.len())
                .map(|b| {
                    if l.only.is_some_and(|m| !m.get(b)) {
                        return -1.0;
                    }
                    l.front.ray_threshold(b, l.threshold).unwrap_or(-1.0)
                })
                .collect()
        });
        let mut vols = Vec::with_capacity(setup.vols.len());
        let mut levels = Vec::new();
        let mut tf = Vec::with_capacity(setup.vols.len() * nb * TF_SIZE);
        self.pre
            .update(setup.vols.iter().map(|v| v.pre.as_deref()))?;
        // Records of `tf` follow the pre-integration tables in the buffer.
        let off = self.pre.data.len();
        let mut bits = vec![0u32; (self.entries as usize).div_ceil(32)];
        for (i, v) in setup.vols.iter().enumerate() {
            debug_assert_eq!(v.ds as usize, i);
            let nl = v.level_t.len();
            let level_t = level_t_array(&v.level_t);
            let t0 = &v.tables[0];
            // Step tables, then (with slices) the straight table: bases are taken as built.
            let tf_base = (off + tf.len()) as u32;
            for t in &v.tables {
                if t.entries.len() != TF_SIZE {
                    bail!(
                        "the GPU caster needs transfer-function tables of {TF_SIZE} entries, got {}",
                        t.entries.len()
                    );
                }
                tf.extend_from_slice(&t.entries);
            }
            let base = self.table_base[i];
            let (t, no_data) = self.types[i];
            let (vflags, vno_data) = self.format.volume_flags(t, no_data);
            for (j, &tr) in v.transparent.iter().enumerate() {
                if tr {
                    let g = base as usize + j;
                    bits[g / 32] |= 1 << (g % 32);
                }
            }
            levels.extend(level_records(v.table));
            // Slices (and horizons by volume) are coloured by the straight transfer function.
            if v.slices.len() > MAX_SLICES {
                bail!(
                    "the GPU caster draws at most {MAX_SLICES} slices per volume, got {}",
                    v.slices.len()
                );
            }
            // One record per slice, after the tables.
            let slice_base = (off + tf.len()) as u32;
            tf.extend(
                v.slices
                    .iter()
                    .map(|s| [s.axis as f32, s.index, s.opacity, 0.0]),
            );
            let mut straight_base = 0;
            // Slices, and horizons coloured by this volume, read its straight colours.
            let coloring = setup
                .hors
                .iter()
                .any(|h| h.attribute.map(|a| a.0) == Some(i));
            if !v.slices.is_empty() || coloring {
                if v.tf.table.len() != TF_SIZE {
                    bail!(
                        "the GPU caster needs transfer-function tables of {TF_SIZE} entries, got {}",
                        v.tf.table.len()
                    );
                }
                straight_base = (off + tf.len()) as u32;
                tf.extend_from_slice(&v.tf.table);
            }
            // Pre-integration: laid out at the start of the buffer (`PreRegion`).
            let pre_base = if v.pre.is_some() { self.pre.base[i] } else { 0 };
            vols.push(VolumeParams {
                m0: v.m[0],
                core: v.core,
                m1: v.m[1],
                border: v.border,
                m2: v.m[2],
                page: v.page as u32,
                c: v.c,
                n_levels: nl as u32,
                hi: v.hi,
                table_base: base,
                level_base: self.level_base[i],
                tf_base,
                tf_scale: t0.scale,
                tf_offset: t0.offset,
                tf_last: t0.last,
                pool_base: 0,
                flags: vflags
                    | if v.invisible {
                        strata_common::gpu::VOLUME_INVISIBLE
                    } else {
                        0
                    }
                    | if v.pre.is_some() {
                        strata_common::gpu::VOLUME_PREINTEGRATED
                    } else {
                        0
                    },
                no_data: vno_data,
                level_t,
                n_slices: v.slices.len() as u32,
                straight_base,
                slice_base,
                pre_base,
            });
        }
        let mut hors = Vec::with_capacity(setup.hors.len());
        let mut hbounds = Vec::new();
        for (j, h) in setup.hors.iter().enumerate() {
            let ds = self.volumes + j;
            debug_assert_eq!(h.ds as usize, ds);
            let nl = h.level_t.len();
            let level_t = level_t_array(&h.level_t);
            levels.extend(level_records(h.table));
            let bounds_base = hbounds.len() as u32;
            // All-hole tiles (NaN bounds) become min > max: the shader skips them without
            // comparing NaNs, which GPU compilers may assume away.
            hbounds.extend(h.bounds.iter().map(
                |&[lo, hi]| {
                    if lo <= hi {
                        [lo, hi]
                    } else {
                        [1.0, 0.0]
                    }
                },
            ));
            let mut flags = 0;
            let (mut map_base, mut map_len, mut depth) = (0, 0, [0.0; 2]);
            if let Some((_, no_data)) = h.attribute {
                // The no-data colour where the depth map would start.
                map_base = (off + tf.len()) as u32;
                tf.push([no_data[0], no_data[1], no_data[2], 1.0]);
            }
            if let Some((map, range)) = h.depth_map {
                flags |= HORIZON_DEPTH_MAP;
                map_base = (off + tf.len()) as u32;
                map_len = map.points().len() as u32;
                tf.extend(map.points().iter().map(|p| [p[0], p[1], p[2], 1.0]));
                depth = range;
            }
            if h.lighting {
                flags |= HORIZON_LIGHTING;
            }
            hors.push(HorizonParams {
                m0: h.m[0],
                core: h.core,
                m1: h.m[1],
                border: h.border,
                m2: h.m[2],
                page: h.page as u32,
                c: h.c,
                n_levels: nl as u32,
                color: h.color,
                opacity: h.opacity,
                dims: h.dims,
                table_base: self.table_base[ds],
                level_base: self.level_base[ds],
                bounds_base,
                map_base,
                map_len,
                flags,
                depth_lo: depth[0],
                depth_hi: depth[1],
                pool_base: 0,
                attr_vol: h.attribute.map_or(NO_VOLUME, |(v, _)| v as u32),
                level_t,
            });
        }
        self.caster.sync_frame_tables(
            &bits,
            &levels,
            (self.pre.generation, &self.pre.data),
            &tf,
            &hbounds,
        );
        let out = self.caster.cast(
            &frame,
            &vols,
            &hors,
            setup.variant.compiled,
            occl.as_deref(),
        )?;
        // After the cast, which uploads the occlusion limits.
        stats.uploaded_bytes = self.caster.take_uploaded();
        stats.readback_bytes = out.readback_bytes;
        stats.feedback_bytes = out.feedback_bytes;
        let mut feedback = Feedback::default();
        for &(g, n) in &out.feedback {
            if let Some(key) = self.key_of(g) {
                *feedback.coverage.entry(key).or_insert(0) += n;
            }
        }
        let cast = CastStats {
            rays: out.rays,
            samples: out.samples,
            skipped: out.skipped,
            hits: out.hits,
            terminated: out.terminated,
        };
        let image = PartialImage {
            width: setup.width,
            height: setup.height,
            rect: r,
            pixels: out.pixels,
        };
        Ok((image, feedback, cast, stats))
    }

    /// The page key of global page-table entry `g`.
    fn key_of(&self, g: u32) -> Option<u64> {
        if g >= self.entries {
            return None;
        }
        let ds = self.table_base.partition_point(|&b| b <= g) - 1;
        let p = &self.pyramids[ds];
        let mut local = g - self.table_base[ds];
        for l in 0..p.level_count() {
            let b = p.level(l).bricks;
            let n = b[0] * b[1] * b[2];
            if local < n {
                let brick = [local % b[0], local / b[0] % b[1], local / (b[0] * b[1])];
                return Some(p.id(l, brick).with_dataset(ds as u16).0);
            }
            local -= n;
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::PreRegion;
    use std::sync::Arc;
    use strata_common::tf::{PreintTable, PREINT_SIZE};

    fn table(v: f32) -> Arc<PreintTable> {
        let n = PREINT_SIZE * PREINT_SIZE;
        Arc::new(PreintTable {
            entries: vec![[v; 4]; n],
            half_entries: vec![[v / 2.0; 4]; n],
            scale: v,
            offset: 0.5,
            last: (PREINT_SIZE - 1) as f32,
        })
    }

    #[test]
    fn pre_region_is_laid_out_once_per_set_of_tables() {
        let n = PREINT_SIZE * PREINT_SIZE;
        let (a, b, c) = (table(1.0), table(2.0), table(3.0));
        let mut r = PreRegion::default();
        // Volume 0 plain, volume 1 with two bands, volume 2 with one.
        let pres = [
            None,
            Some(vec![a.clone(), b.clone()]),
            Some(vec![c.clone()]),
        ];
        r.update(pres.iter().map(|p| p.as_deref())).unwrap();
        assert_eq!(r.generation, 1);
        assert_eq!(r.base, vec![0, 0, (1 + 4 * n) as u32]);
        assert_eq!(r.data.len(), 1 + 4 * n + 1 + 2 * n);
        // Header, band 0 whole and half, band 1 whole and half; then volume 2.
        assert_eq!(r.data[0], [1.0, 0.5, (PREINT_SIZE - 1) as f32, 0.0]);
        assert_eq!(r.data[1], [1.0; 4]);
        assert_eq!(r.data[1 + n], [0.5; 4]);
        assert_eq!(r.data[1 + 2 * n], [2.0; 4]);
        assert_eq!(r.data[1 + 3 * n], [1.0; 4]);
        assert_eq!(
            r.data[r.base[2] as usize],
            [3.0, 0.5, (PREINT_SIZE - 1) as f32, 0.0]
        );
        // The same tables again: nothing laid out, the generation kept.
        let again = [
            None,
            Some(vec![a.clone(), b.clone()]),
            Some(vec![c.clone()]),
        ];
        r.update(again.iter().map(|p| p.as_deref())).unwrap();
        assert_eq!(r.generation, 1);
        // Equal contents in another table (a new transfer function that happens to match)
        // are laid out again: identity, not contents, is the key.
        let other = [
            None,
            Some(vec![a.clone(), table(2.0)]),
            Some(vec![c.clone()]),
        ];
        r.update(other.iter().map(|p| p.as_deref())).unwrap();
        assert_eq!(r.generation, 2);
        // Fewer volumes pre-integrated.
        let fewer: [Option<Vec<Arc<PreintTable>>>; 3] = [None, None, Some(vec![c])];
        r.update(fewer.iter().map(|p| p.as_deref())).unwrap();
        assert_eq!((r.generation, r.base.clone()), (3, vec![0, 0, 0]));
        assert_eq!(r.data.len(), 1 + 2 * n);
        // A malformed table is refused and leaves nothing that matches.
        let bad = Arc::new(PreintTable {
            entries: vec![[0.0; 4]; 3],
            ..(*a).clone()
        });
        let e = r.update([Some(&[bad][..])].into_iter()).unwrap_err();
        assert!(
            format!("{e}").contains("pre-integrated table of 3 entries"),
            "{e}"
        );
        r.update([Some(&[a][..])].into_iter()).unwrap();
        assert_eq!(r.generation, 5);
    }
}

/// Checks, when the backend opens, that the scene's `entries` page-table entries fit the
/// GPU caster's u32 indices and each of their buffers one storage binding of `binding`
/// bytes: the feedback list, bound whole, takes 8 bytes an entry (the table and the
/// counters 4). Past it every frame would fail at binding, with no fallback to the CPU.
fn tables_fit(entries: u64, binding: u64) -> Result<()> {
    if entries >= u32::MAX as u64 / 2 {
        bail!("the scene's page tables ({entries} entries) exceed the GPU caster's u32 indices");
    }
    let bytes = entries * 8;
    if bytes > binding {
        bail!(
            "the scene's page tables ({entries} entries: {bytes} bytes of feedback list) exceed \
             the adapter's largest storage binding ({binding} bytes); use larger pages or the CPU \
             backend"
        );
    }
    Ok(())
}

#[cfg(test)]
mod table_limit_tests {
    use super::tables_fit;

    #[test]
    fn page_tables_past_one_binding_are_refused_at_open() {
        tables_fit(1000, 8000).unwrap();
        let e = tables_fit(1001, 8000).unwrap_err().to_string();
        assert!(e.contains("8008 bytes") && e.contains("8000 bytes"), "{e}");
        assert!(tables_fit(u32::MAX as u64, u64::MAX).is_err());
    }
}
